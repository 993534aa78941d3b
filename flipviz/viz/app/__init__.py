"""The viser browser app: `app.py` (App, the tabs' owner), one module per panel, `session.py` (the runs
the app trains), `mirror/` (the Mirror tab). Imports the shared floor, `rerun/` and `export/`."""
