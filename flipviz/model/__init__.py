"""The model layer: radiance fields, volume rendering, the objective, BARF-style pose refinement.

| module           | holds                                                              |
|------------------|--------------------------------------------------------------------|
| grid_field.py    | `GridConfig`, `GridField`: the dense voxel grid (default, fast)    |
| nerf_field.py    | `NerfConfig`, `NerfField`: the vanilla NeRF MLP (the paper's)      |
| encoding.py      | positional encoding                                                |
| renderer.py      | volume rendering (Eqn. 1) and the rendered variance beta_hat^2     |
| radiance.py      | `ModelConfig`, `RadianceModel`: a field + the renderer             |
| objective.py     | `Objective`: MSE and the uncertainty NLL of Sec. IV-C, with warm-up |
| pose_refine.py   | `PoseRefiner`: per-camera se(3) corrections (BA)                   |
| optim.py         | Adam and the exponential learning-rate decay                       |
| fit.py           | the minimal fitting loop                                           |
"""

from flipviz.model.grid_field import GridConfig
from flipviz.model.nerf_field import NerfConfig
from flipviz.model.objective import Objective, psnr
from flipviz.model.pose_refine import PoseRefiner
from flipviz.model.radiance import ModelConfig, RadianceModel

__all__ = ["GridConfig", "NerfConfig", "ModelConfig", "RadianceModel", "Objective", "PoseRefiner", "psnr"]
