"""The flipviz browser app: `python app.py --scene chair` (then open the printed URL).

Trains a run in the background and shows it live in viser; see `flipviz.viz.viser_app`.
"""

import tyro

from flipviz.viz.viser_app import AppConfig, run_app

if __name__ == "__main__":
    run_app(tyro.cli(AppConfig, description=__doc__))
