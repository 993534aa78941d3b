"""flipviz: interactive visual debugging and teaching for the NeRF method "Just Flip"."""

import os as _os

# OpenMP threads spin while waiting by default; on a busy 2-core machine (the app's render thread,
# bench workers, other processes) that made steps ~10x slower. Must be set before torch loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
