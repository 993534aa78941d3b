"""The exceptions every layer may raise to the CLI: bad user input, and a stop signal."""

import re
import signal

MAX_MESSAGE = 400  # characters: a message quotes input (a value, a path) that may be huge


class UserError(ValueError):
    """Bad input from the user: an option, a file, a folder. The CLI prints it in one line (exit 2).

    The message is made one line whatever it quotes (a tensor's repr spans lines), and at most
    MAX_MESSAGE characters. Internal bugs are never UserErrors, so they keep their traceback.
    """

    def __init__(self, message: str = "") -> None:
        line = re.sub(r"\s*\n\s*", " ", str(message)).strip()
        super().__init__(line if len(line) <= MAX_MESSAGE else line[: MAX_MESSAGE - 3] + "...")


class Interrupted(KeyboardInterrupt):
    """A stop signal (SIGTERM, SIGHUP, or one a bench worker received), raised where Ctrl-C would be,
    so it stops as gracefully as Ctrl-C; the CLI exits with 128 + its number."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
