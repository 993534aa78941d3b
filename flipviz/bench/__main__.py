"""`python -m flipviz.bench ...`: the same as `flipviz bench ...`."""

import sys

from flipviz.cli import run

if __name__ == "__main__":
    run(["bench", *sys.argv[1:]])
