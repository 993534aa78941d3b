"""The flipviz browser app: `python app.py --scene chair` (then open the printed URL).

Trains a run in the background and shows it live in viser; see `flipviz.viz.app.app`. The same
as `flipviz app ...`: bad input is one line, and a Ctrl-C, even during the first imports, stops it
gracefully.
"""

import sys

from flipviz.cli import run

if __name__ == "__main__":
    run(["app", *sys.argv[1:]])
