"""Body models (no ROS): the BodyModel interface, anny and SMPL backends, parts."""
from smpl_depth_ros.body.base import BodyModel, BodyOutput  # noqa: F401


def load_body_model(backend: str = 'anny', model_path: str | None = None, device='cpu',
                    dtype=None):
    """Construct a body model by backend name.

    Args:
        backend: 'anny' (embedded default) or 'smpl' (the user's own model file, from
            `model_path` or the SMPL_MODEL_PATH environment variable).
    """
    import torch
    dtype = dtype or torch.float32
    if backend == 'anny':
        from smpl_depth_ros.body.anny_model import AnnyBody
        return AnnyBody(model_path, dtype=dtype).to(device)
    if backend == 'smpl':
        from smpl_depth_ros.body.smpl_model import SMPLBody
        return SMPLBody(model_path, dtype=dtype).to(device)
    raise ValueError(f"unknown body model backend {backend!r} (expected 'anny' or 'smpl')")
