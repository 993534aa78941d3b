"""What a class opens offline: `video.py` (orbit and fly-through videos) and `report.py` (the run's
HTML page). Imports no viser."""
