"""mip-NeRF 360 scene contraction of radii about the camera centre (paper eq. 10) and its closed-form inverse.

``|x| <= 1`` is kept, ``|x| > 1`` goes to radius ``2 - 1/|x|`` in the same direction; radius ``t >= 2`` has no
preimage. Any leading batch shape; dtype and device kept.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from s2camp_ns.core.validation import check_range

__all__ = ["contract_radius", "uncontract_radius"]


def contract_radius(radius: Float[Tensor, "*batch"]) -> Float[Tensor, "*batch"]:
    """Contracted radius ``s = r`` for ``r <= 1`` else ``2 - 1/r`` (radial part of paper eq. 10)."""
    check_range("radius", radius, low=0.0)
    # both torch.where branches are evaluated: keep 1/r finite at r = 0
    safe = radius.clamp_min(1.0)
    return torch.where(radius <= 1.0, radius, 2.0 - 1.0 / safe)


def uncontract_radius(t: Float[Tensor, "*batch"]) -> Float[Tensor, "*batch"]:
    """``r = t`` for ``t <= 1`` else ``1 / (2 - t)`` (paper eq. 10); ValueError outside ``[0, 2)``."""
    check_range("t", t, low=0.0, high=2.0, high_inclusive=False)
    far = t.clamp_min(1.0)  # the discarded branch of torch.where must stay finite as well
    return torch.where(t <= 1.0, t, 1.0 / (2.0 - far))
