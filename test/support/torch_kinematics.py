"""pytorch-kinematics chains built from the package URDF: the independent FK/Jacobian cross-check of the numpy
kinematics in ``mds_ach.kinematics.model``.

Test-only (torch and pytorch-kinematics are in requirements-dev.txt, ~750 MB that no running system needs).
The chain is built from ``mds_ach.kinematics.model``'s own URDF parse rather than ``pk.build_chain_from_urdf``:
pytorch-kinematics parses origins in float32, which would cost ~1e-8 m of accuracy even after ``.to(float64)``
(``test_urdf`` also checks pytorch-kinematics' own loader, to 1e-6).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import pytorch_kinematics as pk
import torch

from mds_ach.kinematics import model as kinematics

_REVOLUTE = ("revolute", "continuous")


def torch_chain(arm: str | int | None = None, dtype: Any = None, device: Any = "cpu") -> Any:
    """With ``arm`` the serial chain torso -> ``<arm>_tool`` (joint order [SP, SR, SY, EP, WY, WR]); without it
    the whole tree (``get_joint_parameter_names()`` gives its joint order). Default dtype float64."""
    return _chain(None if arm is None else kinematics.arm_name(arm), dtype or torch.float64, str(device))


@lru_cache(maxsize=8)
def _chain(arm: str | None, dtype: Any, device: str) -> Any:
    model = kinematics.load_model()
    children: dict[str, list[kinematics.Joint]] = {}
    for j in model.joints.values():
        children.setdefault(j.parent, []).append(j)

    def frame(link: str, joint: kinematics.Joint | None) -> Any:
        f = pk.Frame(link, link=pk.Link(link))
        if joint is not None:
            f.joint = pk.Joint(
                joint.name,
                offset=pk.Transform3d(matrix=torch.as_tensor(joint.origin, dtype=dtype), dtype=dtype, device=device),
                joint_type="revolute" if joint.type in _REVOLUTE else joint.type,
                axis=torch.as_tensor(joint.axis, dtype=dtype),
                dtype=dtype,
                device=device,
                limits=(joint.lower, joint.upper) if joint.actuated else None,
                velocity_limits=(-joint.velocity, joint.velocity) if joint.actuated else None,
                effort_limits=(-joint.effort, joint.effort) if joint.actuated else None,
            )
        f.children = [frame(j.child, j) for j in children.get(link, ())]
        return f

    chain = pk.Chain(frame(model.root, None), dtype=dtype, device=device)
    if arm is not None:
        chain = pk.SerialChain(chain, f"{arm}_tool", kinematics.ARM_ROOT, dtype=dtype, device=device)
    return chain


def torch_fk(q: torch.Tensor | np.ndarray, arm: str | int) -> torch.Tensor:
    """Batched tool poses (B, 4, 4) of one arm in the torso frame."""
    chain = torch_chain(arm)
    return chain.forward_kinematics(torch.as_tensor(q, dtype=chain.dtype, device=chain.device)).get_matrix()


def torch_jacobian(q: torch.Tensor | np.ndarray, arm: str | int) -> torch.Tensor:
    """Batched geometric Jacobians (B, 6, 6) at the tool point, torso frame."""
    chain = torch_chain(arm)
    return chain.jacobian(torch.as_tensor(q, dtype=chain.dtype, device=chain.device))
