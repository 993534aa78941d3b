"""Rerun: the training observer (`observer.py`), its blueprint, the web viewer, and `flipviz compare`.
Imports no viser."""
