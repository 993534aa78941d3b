"""The Mirror tab: `tab.py` (the lesson: plane, preview, estimate), `curves.py` (over training),
`scores.py` (each mirror scored against the model)."""
