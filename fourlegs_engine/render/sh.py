"""View-dependent colour from real spherical harmonics (Inria 3DGS coefficient layout).

Basis order and signs follow the common 3DGS convention: degree l uses coefficients l² … (l+1)²−1,
evaluated at the unit direction from the camera centre to the Gaussian; RGB = max(Σ c·Y + 0.5, 0).
"""
from __future__ import annotations

import torch

from ..errors import InputError
from ..scene.camera import Camera

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis values at unit directions: (N,3) -> (N, (degree+1)²)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(sh: torch.Tensor, means: torch.Tensor, camera: Camera) -> torch.Tensor:
    """RGB (N,3) of SH coefficients (N,K,3), K in {1,4,9,16}, seen from ``camera``."""
    K = sh.shape[1]
    degrees = {1: 0, 4: 1, 9: 2, 16: 3}
    if K not in degrees:
        raise InputError(f"has {K} coefficients per channel, expected 1, 4, 9 or 16", field="sh")
    centre = torch.as_tensor(camera.center, dtype=means.dtype, device=means.device)
    d = means - centre
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(d, degrees[K]).to(sh.dtype)  # (N,K)
    return ((basis[:, :, None] * sh).sum(1) + 0.5).clamp_min(0.0)


def frame_colors(frame, camera: Camera) -> torch.Tensor:
    """(N,3) colours of a GaussianFrame: its ``colors``, else its SH evaluated for ``camera``."""
    if frame.colors is not None:
        return frame.colors
    if frame.sh is None:
        raise InputError("the frame has neither colors nor SH coefficients", field="colors")
    return eval_sh(frame.sh, frame.means, camera)
