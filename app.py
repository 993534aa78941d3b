"""The flipviz browser app: `python app.py --scene chair` (then open the printed URL).

Trains a run in the background and shows it live in viser; see `flipviz.viz.viser_app`.
"""

import sys

import tyro

from flipviz.cli import guarded
from flipviz.viz.viser_app import AppConfig, run_app

if __name__ == "__main__":
    cfg = tyro.cli(AppConfig, description=__doc__)
    sys.exit(guarded(lambda: run_app(cfg) or 0))
