"""The quaternion field q(x) and the scale-ratio field s(x) (SPEC step 5): SIREN networks, or free
per-element values (the ablation of the Q-S networks)."""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from neuralslicer.neural.config import NetworkConfig


class SineLayer(nn.Module):
    """Linear layer followed by sin(omega * .), with Sitzmann et al. initialisation."""

    def __init__(self, in_features: int, out_features: int, omega: float, first: bool) -> None:
        super().__init__()
        self.omega = omega
        self.linear = nn.Linear(in_features, out_features)
        bound = 1.0 / in_features if first else math.sqrt(6.0 / in_features) / omega
        with torch.no_grad():
            self.linear.weight.uniform_(-bound, bound)
            self.linear.bias.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """sin(omega (W x + b))."""
        return torch.sin(self.omega * self.linear(x))


class Siren(nn.Module):
    """SIREN MLP R^3 -> R^k whose zero-initialised output layer makes it start at exactly 0."""

    def __init__(self, out_features: int, cfg: NetworkConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = [SineLayer(3, cfg.hidden_features, cfg.omega_0, first=True)]
        for _ in range(cfg.hidden_layers - 1):
            layers.append(
                SineLayer(cfg.hidden_features, cfg.hidden_features, cfg.omega_hidden, first=False)
            )
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(cfg.hidden_features, out_features)
        with torch.no_grad():
            self.head.weight.zero_()
            self.head.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x : (n, 3) in [-1, 1]^3 -> (n, k)."""
        return self.head(self.body(x))


class ElementTable(nn.Module):
    """Free values per cage tet, R^3 -> R^k only at the tets' centroids: one trainable row per element."""

    def __init__(self, n_elements: int, initial: list[float]) -> None:
        super().__init__()
        rows = torch.tensor(initial, dtype=torch.float32).expand(n_elements, len(initial))
        self.values = nn.Parameter(rows.clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x : (m, 3), the m element centroids in element order -> the table (m, k)."""
        if x.shape[0] != self.values.shape[0]:
            raise ValueError(
                f"per-element q, s are defined at the {self.values.shape[0]} cage-tet centroids only; "
                f"got {x.shape[0]} points")
        return self.values


class DeformationFields(nn.Module):
    """The two fields q(x) (unit quaternion, w first) and s(x) (positive scale ratios).

    With ``cfg.kind == 'siren'`` they are SIREN networks; inputs are model-space points, normalised
    to [-1, 1]^3 by the cage's bounding box (kept as buffers, so that they are part of the state
    dict). With ``cfg.kind == 'per_element'`` they are tables of ``n_elements`` free rows (raw
    quaternion, pre-activation scale) and are evaluated at the cage-tet centroids only. Either way
    q = (1,0,0,0) and s = (1,1,1) exactly at initialisation: the identity mapping, planar layers G = z.
    """

    def __init__(self, cfg: NetworkConfig, bounds: np.ndarray, n_elements: int | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        q_offset = [1.0, 0.0, 0.0, 0.0]
        if cfg.kind == "per_element":
            if n_elements is None:
                raise ValueError("the per_element parameterisation needs the number of cage tets (n_elements)")
            # the raw quaternion itself starts at (1,0,0,0), so the weights never all vanish (the DC3
            # correction caps its step relative to the weight norm)
            self.q_net: nn.Module = ElementTable(n_elements, q_offset)
            self.s_net: nn.Module = ElementTable(n_elements, [0.0, 0.0, 0.0])
            q_offset = [0.0, 0.0, 0.0, 0.0]
        else:
            self.q_net = Siren(4, cfg)
            self.s_net = Siren(3, cfg)
        bounds = np.asarray(bounds, dtype=np.float64)
        centre = 0.5 * (bounds[0] + bounds[1])
        half = np.maximum(0.5 * (bounds[1] - bounds[0]), 1e-12)
        self.register_buffer("centre", torch.as_tensor(centre, dtype=torch.float32))
        self.register_buffer("half_extent", torch.as_tensor(half, dtype=torch.float32))
        self.register_buffer("q_offset", torch.tensor(q_offset))
        self.log_max_scale = math.log(cfg.max_scale)

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """Model-space points (n,3) -> [-1,1]^3 by the cage bounding box."""
        return (x - self.centre.to(x.dtype)) / self.half_extent.to(x.dtype)

    def raw_quaternion(self, x: torch.Tensor) -> torch.Tensor:
        """Unnormalised quaternion q(x) (n,4): (1,0,0,0) + network output, or the per-element row."""
        return self.q_offset.to(x.dtype) + self.q_net(self.normalise(x))

    def scale(self, x: torch.Tensor) -> torch.Tensor:
        """Scale ratios s(x) (n,3) = exp(log(max) tanh(out / log(max))), in (1/max, max)."""
        out = self.s_net(self.normalise(x))
        return torch.exp(self.log_max_scale * torch.tanh(out / self.log_max_scale))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(unit quaternion (n,4), scale ratios (n,3)) at model-space points x (n,3)."""
        q = self.raw_quaternion(x)
        q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return q, self.scale(x)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (n,3,3) of unit quaternions q (n,4) = (w, x, y, z)."""
    w, x, y, z = q.unbind(dim=1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=1,
    ).reshape(-1, 3, 3)


def quaternion_to_z_row(q: torch.Tensor) -> torch.Tensor:
    """Third rows (n,3) of the rotation matrices of unit quaternions q (n,4) = (w, x, y, z): the entries of
    :func:`quaternion_to_matrix` that the height G needs, computed by the same expressions."""
    w, x, y, z = q.unbind(dim=1)
    return torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=1)
