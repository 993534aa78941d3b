"""The `flipviz` command line: one tyro CLI with a subcommand per tool.

flipviz train --scene chair --method flip+u --config 3
flipviz app --scene mug                  (same as `python app.py --scene mug`)
flipviz bench --scenes chair,lego --data-root path/to/nerf_synthetic
flipviz export-scene chair out/chair
flipviz export-scene chair-turned out/drive --trajectory driveby
flipviz video RUN [RUN_B] --path unobserved|orbit|keyframes.json [--gif out.gif]
flipviz compare RUN_A RUN_B [--serve]     (their Rerun recordings side by side)
flipviz report RUN                         (a self-contained HTML page of the run)
flipviz score RUN --eval-views orbit --eval-tune-steps 100   (scored again: the released code's protocol)
"""

from __future__ import annotations

import atexit
import contextlib
import io
import itertools
import os
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, NoReturn, Union

import tyro

from flipviz.errors import Interrupted, UserError
from flipviz.files import STOP_SIGNALS
from flipviz.options import check_ranges
from flipviz.training.config import PRESETS, EvalConfig, EvalEvery, EvalSteps, Res, TrainConfig, preset_config


@dataclass
class ExportScene:
    """Write a built-in scene as data: its orbit in the Blender format, or a robot's drive-by capture
    in the nerfstudio format (train on it with `flipviz train --data DIR` or `python app.py --data DIR`)."""

    scene: Annotated[str, tyro.conf.Positional]
    """Built-in scene name."""
    out_dir: Annotated[Path, tyro.conf.Positional]
    """Folder to write."""
    res: Res = 100
    """Image width in pixels."""
    trajectory: Literal["orbit", "driveby"] = "orbit"
    """orbit: the protocol's first turn (transforms_test.json); driveby: a one-sided robot path with
    varying height and distance, plus held-out views of the far side (transforms.json)."""


@dataclass
class Score:
    """Score a finished run again, under another protocol: e.g. the released code's (`--eval-views orbit
    --eval-tune-steps 100`, each test pose tuned on its ground truth). Prints the scores and writes them
    to <run>/scores_<views>_tune<steps>.json; the run's own metrics.json is left as it is."""

    run: Annotated[Path, tyro.conf.Positional]
    """Run folder (with its checkpoint.pt)."""
    eval_views: Literal["unobserved", "orbit"] = EvalConfig.eval_views
    """unobserved: the protocol's 8 test views; orbit: every orbit view the run did not train on."""
    eval_tune_steps: EvalSteps = EvalConfig.eval_tune_steps
    """Adam steps that tune each test pose on its ground truth first (the released code: 100)."""
    eval_every: EvalEvery = EvalConfig.eval_every
    """Score every n-th of those views (1: all)."""
    device: str | None = None


def _score(cmd: Score) -> int:
    from flipviz.files import cannot_write, write_json
    from flipviz.training.saved_run import open_run, score

    run = open_run(cmd.run, cmd.device)
    m = score(run, cmd.eval_views, cmd.eval_tune_steps, cmd.eval_every)
    every = f"_every{cmd.eval_every}" if cmd.eval_every > 1 else ""
    out = run.run_dir / f"scores_{cmd.eval_views}_tune{cmd.eval_tune_steps}{every}.json"
    with cannot_write(out, "the scores"):
        write_json(out, m)
    print(
        f"{run.run_dir.name}: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.3f} on {m['scored_views']} views "
        f"({cmd.eval_views}, poses tuned {cmd.eval_tune_steps} steps); wrote {out}"
    )
    return 0


def _run_train(cfg: TrainConfig) -> int:
    """`flipviz train`: a progress bar, the Rerun recording, one summary line, how to open it."""
    import logging

    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from flipviz.training.artifacts import check_named_files
    from flipviz.training.progress import ProgressObserver
    from flipviz.training.run import make_trainer
    from flipviz.training.trainer import default_run_dir

    logging.basicConfig(level=logging.WARNING, format="[flipviz] %(message)s")
    cfg.validate()
    check_named_files(cfg)  # before the scene is built: a refusal comes at once
    if cfg.output.out is None:
        cfg.output.out = default_run_dir(cfg)

    def say(text: str) -> None:  # what setup and a slow evaluation do (a line above the bar; "": over)
        if text:
            tqdm.write(f"[flipviz] {text}", file=sys.stderr)

    trainer = make_trainer(cfg, on_phase=say)  # inputs checked, the run folder locked before anything is written
    trainer.add_observer(ProgressObserver())
    rerun = None
    try:
        if not cfg.output.no_rrd or cfg.output.rerun_serve:
            from flipviz.viz.rerun.observer import make_rerun_observer

            rerun = make_rerun_observer(cfg, cfg.output.out, bake=trainer.point_cloud)
            trainer.add_observer(rerun)
        with logging_redirect_tqdm():  # a warning during training is a line of its own above the bar
            metrics = trainer.run()  # Ctrl-C inside the loop ends it with status "stopped"
        print(f"[flipviz] run folder: {cfg.output.out}")
        if "psnr" in metrics:
            lp = metrics.get("lpips")
            lp_s = f"{lp:.3f}" if isinstance(lp, float) else f"{lp} ({metrics.get('lpips_reason', '')})"
            print(
                f"[flipviz] {metrics['status']}: PSNR {metrics['psnr']:.2f} dB, "
                f"SSIM {metrics['ssim']:.3f}, LPIPS {lp_s}, "
                f"{metrics.get('train_seconds', 0):.0f} s, {metrics['steps']} steps; scored in {cfg.eval.words()}"
            )
            if "iou" in metrics:
                depth = f", depth error {metrics['depth_abs']:.3f}" if "depth_abs" in metrics else ""
                print(
                    f"[flipviz] the object: silhouette IoU {metrics['iou']:.3f}, "
                    f"PSNR inside it {metrics['psnr_object']:.2f} dB{depth}"
                )
        elif metrics.get("message"):
            print(f"[flipviz] {metrics['status']}: {metrics['message']}")
        plane = metrics.get("plane", {})
        if "refined" in plane:
            err = ""
            if "refined_error_deg" in plane:  # the scene's true plane is known
                err = (
                    f"; off the true plane {plane['error_deg']:.2f}° / {plane['error_offset']:.3f} before, "
                    f"{plane['refined_error_deg']:.2f}° / {plane['refined_error_offset']:.3f} after"
                )
            print(
                f"[flipviz] mirror plane refined during training: turned {plane['refined_change_deg']:.2f}°, "
                f"moved {plane['refined_change_offset']:.3f}{err}"
            )
        if plane.get("dropped_at") is not None:
            print(
                f"[flipviz] mirrored views dropped at step {plane['dropped_at']}: they disagreed with the inputs "
                f"(disagreement {plane['disagreement']:.2f} > --disagreement-limit {cfg.flip.disagreement_limit:g})"
                + ("; the field then trained afresh on the inputs alone, as B/L" if plane.get("restarted_at") else "")
            )
        elif plane.get("trained") is False:
            print(
                f"[flipviz] trained without mirrored views: the estimated plane's confidence is "
                f"{metrics['plane']['confidence']:.2f} (--unconfident-plane use keeps them)"
            )
        if rerun is not None and rerun.opts.path is not None:
            print(f"[flipviz] recording: rerun {rerun.opts.path}")
        if rerun is not None and cfg.output.rerun_serve:
            _serve_until_interrupted(rerun.viewer_url)
    finally:  # also on Ctrl-C before the loop: the folder is free again, the recording readable
        trainer.close()
        if rerun is not None:
            rerun.close()
    return 0 if metrics.get("status", "finished") in ("finished", "stopped") else 1


def _serve_until_interrupted(url: str | None) -> None:
    print(f"training done; Rerun web viewer still at {url} (Ctrl-C to quit)", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass


def _export(cmd: ExportScene) -> int:
    from flipviz.data.blender import export_scene
    from flipviz.data.driveby import export_driveby
    from flipviz.files import cannot_write

    with cannot_write(cmd.out_dir, "the scene into"):
        (export_driveby if cmd.trajectory == "driveby" else export_scene)(cmd.scene, cmd.out_dir, res=cmd.res)
    print(f"wrote {cmd.scene} ({cmd.trajectory}) to {cmd.out_dir}")
    return 0


def main(argv: list[str] | None = None) -> int:
    try:  # the first imports (torch, viser, rerun) take seconds: a Ctrl-C there is one line too
        cmd = parse_command(argv)
        check_ranges(cmd)  # every command's numbers, before it locks, writes or loads anything
    except KeyboardInterrupt:
        print("flipviz: interrupted (SIGINT)", file=sys.stderr)
        return 128 + signal.SIGINT
    except UserError as e:
        print(f"flipviz: error: {e}", file=sys.stderr)
        return 2
    return guarded(lambda: _dispatch(cmd))


def run(argv: list[str] | None = None) -> NoReturn:
    """The process's entry (`flipviz`, `python app.py`): exit with main's code.

    Everything is saved once main returns, so a Ctrl-C, SIGTERM or SIGHUP that arrives while Python
    shuts down (joining threads, tearing down torch) ends the exit at once with that same code. It no
    longer prints a traceback or turns the exit code into "killed by SIGINT"."""
    try:
        code = main(argv)
    except KeyboardInterrupt:  # a Ctrl-C between main's own handling and here
        code = 128 + signal.SIGINT
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda signum, frame: os._exit(code))
    atexit.register(lambda: [signal.signal(sig, signal.SIG_IGN) for sig in STOP_SIGNALS])  # Python's teardown resets
    # the handlers it installed to the default (killed by the signal); an ignored signal stays ignored
    sys.exit(code)


def parse_command(argv: list[str] | None) -> object:
    """The subcommand's config from `argv`, in one parse. A `--preset` (train, app, bench) gives the
    defaults it parses with (its whole config: `preset_config`), so every option you pass wins."""
    from flipviz.bench import BenchConfig
    from flipviz.viz.app.app import AppConfig
    from flipviz.viz.export.report import ReportConfig
    from flipviz.viz.export.video import VideoConfig
    from flipviz.viz.rerun.compare import CompareConfig

    commands = {
        "train": TrainConfig,
        "app": AppConfig,
        "bench": BenchConfig,
        "export-scene": ExportScene,
        "video": VideoConfig,
        "compare": CompareConfig,
        "report": ReportConfig,
        "score": Score,
    }

    def parse(defaults: dict[type, object]) -> object:
        union = tuple(
            Annotated[cls, tyro.conf.subcommand(name, default=defaults.get(cls, tyro.MISSING_NONPROP))]
            for name, cls in commands.items()
        )
        return _parsed(lambda: tyro.cli(Union[union], args=argv, description=__doc__))  # noqa: UP007 (a Union built at run time)

    preset = _preset_named(sys.argv[1:] if argv is None else argv)
    return parse({cls: preset_config(preset, cls) for cls in (TrainConfig, AppConfig, BenchConfig)} if preset else {})


def _preset_named(argv: list[str]) -> str | None:
    """The value of --preset in `argv` (None: not given, or not a preset: the parse then says so)."""
    import argparse

    scan = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    scan.add_argument("--preset")
    seen, _ = scan.parse_known_args(argv)
    return seen.preset if seen.preset in PRESETS and seen.preset != "fast" else None


def _parsed(parse: Callable[[], object]) -> object:
    """tyro's parse, with a bad option as one UserError line instead of tyro's framed box (its first
    paragraph: what is wrong, and what is allowed); --help and the rest print as tyro prints them."""
    box = io.StringIO()
    try:
        with contextlib.redirect_stderr(box):
            parsed = parse()
        sys.stderr.write(box.getvalue())  # any warning tyro printed
        return parsed
    except SystemExit as e:
        if e.code in (0, None):
            sys.stderr.write(box.getvalue())
            raise
        text = [ln.strip(" │╭╮╰╯") for ln in box.getvalue().splitlines()[1:]]  # the box's title line is its kind
        first = itertools.takewhile(lambda ln: ln and set(ln) != {"─"}, text)
        raise UserError(" ".join(first) + " (see --help)") from None


def _dispatch(cmd) -> int:
    from flipviz.bench import BenchConfig, run_bench
    from flipviz.viz.app.app import AppConfig, run_app
    from flipviz.viz.export.report import ReportConfig, write_run_report
    from flipviz.viz.export.video import VideoConfig
    from flipviz.viz.rerun.compare import CompareConfig, run_compare

    if isinstance(cmd, AppConfig):  # AppConfig extends TrainConfig: test it first
        run_app(cmd)
        return 0
    if isinstance(cmd, TrainConfig):
        return _run_train(cmd)
    if isinstance(cmd, BenchConfig):
        print(f"results: {run_bench(cmd)}")
        return 0
    if isinstance(cmd, VideoConfig):
        return _video(cmd)
    if isinstance(cmd, CompareConfig):
        return run_compare(cmd)
    if isinstance(cmd, Score):
        return _score(cmd)
    if isinstance(cmd, ReportConfig):
        print(f"wrote {write_run_report(cmd)} (self-contained: open it in any browser, offline)")
        return 0
    return _export(cmd)


def _video(cmd) -> int:
    from flipviz.viz.export.video import make_video

    mp4, gif = make_video(cmd)
    print(f"wrote {mp4}" + (f" and {gif}" if gif else ""))
    return 0


_received: list[int] = []  # the stopping signals received by this process, in order


def _on_signal(signum: int, frame) -> None:
    _received.append(signum)
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Interrupted(signum)


def guarded(fn: Callable[[], int]) -> int:
    """Run a command: bad input is one line on stderr (exit 2); Ctrl-C, SIGTERM and SIGHUP stop it
    gracefully (a training keeps its checkpoint and recording) with exit 128 + the signal's number.

    Only `UserError` is bad input; any other exception is a bug and keeps its traceback.
    """
    main = threading.current_thread() is threading.main_thread()
    before = {sig: signal.signal(sig, _on_signal) for sig in STOP_SIGNALS} if main else {}
    _received.clear()
    try:
        code = fn()
    except UserError as e:  # bad input: one line, no traceback
        print(f"flipviz: error: {e}".splitlines()[0], file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # outside the training loop (setup, loading): no traceback
        signum = _received[0] if _received else getattr(e, "signum", signal.SIGINT)
        print(f"flipviz: interrupted ({signal.Signals(signum).name})", file=sys.stderr)
        return 128 + signum
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
    if _received:  # the training loop caught the signal and stopped gracefully
        print(f"flipviz: stopped by {signal.Signals(_received[0]).name}", file=sys.stderr)
        return 128 + _received[0]
    return code


if __name__ == "__main__":
    run()
