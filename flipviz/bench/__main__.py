"""`python -m flipviz.bench ...`: the same as `flipviz bench ...`."""

import sys

from flipviz.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
