"""Physics feature maps of the PGNNs, SPEC §3 item 1: f_phy(θ_phy, φ) = T₀(φ) + T(φ) θ_phy.

A map returns the parameter-free offset T₀(φ) and the feature rows T(φ) of a regressor batch; the
PGNN (:mod:`pipeline.models.pgnn`) adds its NN part.  Built in: the linear ARX map ([B2] (27)),
the rigid body of [B1] (32) in forward and inverse form, and any plant's physics model
(:class:`PhysicsModelFeatures`).  The built-in maps carry a ``fast_kind`` id for the numba
kernels of :mod:`pipeline.models.fast_pgnn`.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from pipeline.params import schema

KIND = "physics"   # the model option (model.kind, or model=physics) this module's Params checks


@schema
class Params:
    name: str = "physics"


__all__ = ["PhysicsFeatures", "LinearFeatures", "RigidBodyForward", "RigidBodyInverse", "PhysicsModelFeatures",
           "physics_features_for"]

# numba kernel ids of the built-in physics maps (pipeline.models.fast_pgnn._fast_physics)
_KIND_LINEAR, _KIND_RIGID_FWD, _KIND_RIGID_INV, _KIND_RIGID_TERMS, _KIND_RIGID_TERMS_INV = 0, 1, 2, 3, 4


# --------------------------------------------------------------------------------------------
# physics feature maps: f_phy(θ, φ) = T₀(φ) + T(φ) θ
# --------------------------------------------------------------------------------------------
class PhysicsFeatures(nn.Module):
    """Linear-in-parameters physics model on a regressor φ: ``f_phy = T₀(φ) + T(φ) θ``.

    Subclasses set :attr:`param_names` and implement :meth:`features`.  A map used by a
    forward or invertible PGNN must be affine in the most recent input u(t-n_k-1) (the
    analytic inverse [B1] (8), (27) and the Newton start need it); set
    :attr:`affine_in_latest_input` to False otherwise.
    """

    #: names of θ_phy, in order
    param_names: tuple[str, ...] = ()
    #: f_phy is affine in φ[:, n_a] (u(t-n_k-1)) for the forward layout
    affine_in_latest_input: bool = True
    #: id of the numba kernel implementing this map (-1: no fast path)
    fast_kind: int = -1

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def features(self, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return (T₀(φ) [B], T(φ) [B, p]) for a batch φ [B, n_phi]."""
        raise NotImplementedError

    def forward(self, phi: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """f_phy(θ, φ) [B]."""
        off, T = self.features(phi)
        return off + T @ theta

    def physical(self, theta) -> dict[str, float]:
        """Physical parameters from θ_phy (identity naming by default)."""
        return {n: float(v) for n, v in zip(self.param_names, np.asarray(theta, dtype=float))}

    def fast_config(self) -> np.ndarray:
        """Float configuration of the numba kernel (see :func:`_fast_physics`)."""
        raise NotImplementedError(f"{type(self).__name__} has no numba fast path")


class LinearFeatures(PhysicsFeatures):
    """ARX physics: ``f_phy = θᵀ φ`` (T = identity, T₀ = 0), e.g. SPEC §2.4 or [B1] (16).

    Parameters
    ----------
    n_phi : int
        Length of the regressor φ.
    names : sequence of str, optional
        Names of θ (default ``theta_0, theta_1, …``).
    """

    fast_kind = _KIND_LINEAR

    def __init__(self, n_phi: int, names=None):
        super().__init__()
        if n_phi < 1:
            raise ValueError(f"n_phi must be >= 1, got {n_phi}")
        names = tuple(names) if names is not None else tuple(f"theta_{i}" for i in range(n_phi))
        if len(names) != n_phi:
            raise ValueError(f"got {len(names)} names for {n_phi} regressor entries")
        self.param_names = names
        self.n_phi = n_phi

    def features(self, phi):
        return torch.zeros(phi.shape[0], dtype=phi.dtype), phi[:, :self.n_phi]

    def fast_config(self):
        return np.array([float(self.n_phi)])


class RigidBodyForward(PhysicsFeatures):
    """Forward rigid body with viscous and Coulomb friction, [B1] (32) written for y(t).

    With δ the backward difference, n_k = 0 and φ = [y(t-1), y(t-2), …, u(t-1), …]:

        y(t) = 2y(t-1) - y(t-2) + Ts² (u(t-1) - f_v δy(t-1) - f_c sign(δy(t-1))) / m

    linear in θ = [1/m, f_v/m, f_c/m] (SPEC §2.2, ``equation`` noise).  Extra lags in φ
    (n_a > 2, n_b > 1) are ignored by the physics and seen by the NN only.

    Parameters
    ----------
    Ts : float
        Sample time [s].
    n_a : int
        Number of output lags in φ (>= 2); u(t-1) is at ``phi[:, n_a]``.
    """

    param_names = ("inv_m", "f_v_over_m", "f_c_over_m")
    fast_kind = _KIND_RIGID_FWD

    def __init__(self, Ts: float, n_a: int = 2):
        super().__init__()
        if not Ts > 0:
            raise ValueError(f"sample time Ts must be > 0 s, got {Ts}")
        if n_a < 2:
            raise ValueError(f"RigidBodyForward needs n_a >= 2 output lags (δ²y), got {n_a}")
        self.Ts, self.n_a = float(Ts), int(n_a)

    def features(self, phi):
        Ts = self.Ts
        y1, y2, u1 = phi[:, 0], phi[:, 1], phi[:, self.n_a]
        v = (y1 - y2) / Ts  # δy(t-1) [m/s]
        T = Ts ** 2 * torch.stack([u1, -v, -torch.sign(v)], dim=1)
        return 2.0 * y1 - y2, T

    def physical(self, theta):
        th = np.asarray(theta, dtype=float)
        return {"m": 1.0 / th[0], "f_v": th[1] / th[0], "f_c": th[2] / th[0]}

    def fast_config(self):
        return np.array([self.Ts, float(self.n_a)])


class RigidBodyInverse(PhysicsFeatures):
    """Inverse rigid body with viscous and Coulomb friction, [B1] (32) solved for u, n_k = 0.

    With φ'(t) = [y(t+1), y(t), y(t-1), …, u(t-1), …]:

        u(t) = m δ²y(t+1) + f_v δy(t) + f_c sign(δy(t)),   θ = [m, f_v, f_c]

    Parameters
    ----------
    Ts : float
        Sample time [s].
    """

    param_names = ("m", "f_v", "f_c")
    fast_kind = _KIND_RIGID_INV

    def __init__(self, Ts: float):
        super().__init__()
        if not Ts > 0:
            raise ValueError(f"sample time Ts must be > 0 s, got {Ts}")
        self.Ts = float(Ts)

    def features(self, phi):
        Ts = self.Ts
        y0, y1, y2 = phi[:, 0], phi[:, 1], phi[:, 2]
        acc = (y0 - 2.0 * y1 + y2) / Ts ** 2  # δ²y(t+1) [m/s²]
        v = (y1 - y2) / Ts  # δy(t) [m/s]
        return torch.zeros_like(y0), torch.stack([acc, v, torch.sign(v)], dim=1)

    def fast_config(self):
        return np.array([self.Ts])


class PhysicsModelFeatures(PhysicsFeatures):
    """Adapter for a plant's nominal physics model (``pipeline.systems``) exposing
    ``offset(φ)`` and ``features(φ)`` (forward layout) or ``inverse_features(φ')`` (inverse
    layout, offset 0), numpy/torch-agnostic.  Prefer :func:`physics_features_for`, which maps the
    known plants to the built-in maps.

    Numba fast path: only for a measured rigid body with force terms
    (:class:`pipeline.systems.measured.RigidBodyPhysics`) on its direct input, forward layout (kind 3):
    ``y(t) = 2y(t-1) - y(t-2) + Ts² (θ₀ w(t-1) - Σ_j θ_j T_j(y(t-1), δy(t-1)))`` with the terms'
    kernel codes (``kernel_terms``), and inverse layout (kind 4, issue 49):
    ``w = θ'₀ δ²y(t+1) + Σ_j θ'_j T_j(y(t), δy(t))`` on φ' = [y(t+1), y(t), y(t-1), …].  Any other model
    has none (the inversions then use their torch reference, one sample at a time).
    """

    def __init__(self, physics_model, inverse: bool = False):
        super().__init__()
        need = ("inverse_features",) if inverse else ("offset", "features")
        missing = [a for a in need if not hasattr(physics_model, a)]
        if missing:
            raise ValueError(f"{type(physics_model).__name__} has no {missing}; it cannot serve as "
                             "the physics part of a PGNN")
        self.pm = physics_model
        self.inverse = bool(inverse)
        n = len(physics_model.param_names)
        self.param_names = tuple(f"theta'_{i}" for i in range(n)) if inverse \
            else tuple(physics_model.param_names)

    @property
    def fast_kind(self) -> int:
        pm = self.pm
        rigid = (getattr(pm, "physics_law", None) == "rigid_body" and hasattr(pm, "kernel_terms")
                 and not getattr(pm, "averaged_input", True))
        if not rigid:
            return -1
        return _KIND_RIGID_TERMS_INV if self.inverse else _KIND_RIGID_TERMS

    def fast_config(self):
        if self.fast_kind not in (_KIND_RIGID_TERMS, _KIND_RIGID_TERMS_INV):
            return super().fast_config()
        codes, p = self.pm.kernel_terms()
        return np.concatenate([[self.pm.Ts, float(codes.size)], codes.astype(np.float64), p])

    def features(self, phi):
        if self.inverse:
            T = self.pm.inverse_features(phi)
            return torch.zeros(phi.shape[0], dtype=phi.dtype), T
        return self.pm.offset(phi), self.pm.features(phi)

    def physical(self, theta):
        if self.inverse:
            return super().physical(theta)
        return self.pm.physical(np.asarray(theta, dtype=float))


def physics_features_for(physics_model, structure: str, n_a: int, n_b: int, n_k: int = 0,
                         input_is_model_input: bool = False) -> PhysicsFeatures:
    """The PGNN physics map of a plant's nominal physics model for a regressor layout.

    Known plants get the built-in maps with numba kernels: the linear motor's [B1] (32)
    (``LinearMotorPhysics`` with a non-averaged input; average the input beforehand with its
    ``model_input``) → :class:`RigidBodyForward` / :class:`RigidBodyInverse`; ARX
    (``ARXPhysics``) → :class:`LinearFeatures` (forward: θ = [a, b]; inverse: θ' of [B1] (16)).
    Anything else → :class:`PhysicsModelFeatures`.

    ``input_is_model_input``: the data's input is already the physics model's input w
    (``physics_model.model_input(u)``, e.g. the averaged ū of the continuous linear motor),
    so the map is the direct-input one.
    """
    name = type(physics_model).__name__
    inverse = structure == "inverse"
    averaged = getattr(physics_model, "averaged_input", False)
    if name == "LinearMotorPhysics" and (input_is_model_input or not averaged):
        # [B1] (32) is δ²y(t) = (u(t-1) - f_v δy(t-1) - f_c sign δy(t-1))/m: two output lags, one
        # input lag, no pure delay; a regressor that cannot hold it is a config error
        if n_k != 0 or n_a < 2 or n_b < 1:
            raise ValueError(f"the linear motor's physics model [B1] (32) needs n_a >= 2, n_b >= 1 and "
                             f"n_k = 0 in the PGNN regressor, got n_a={n_a}, n_b={n_b}, n_k={n_k}: set "
                             "model.n_a=2 model.n_b=1 model.n_k=0")
        Ts = physics_model.Ts
        return RigidBodyInverse(Ts) if inverse else RigidBodyForward(Ts, n_a)
    if name == "ARXPhysics":
        if (physics_model.n_a, physics_model.n_b, physics_model.n_k) != (n_a, n_b, n_k):
            raise ValueError(f"ARX physics has n_a={physics_model.n_a}, n_b={physics_model.n_b}, "
                             f"n_k={physics_model.n_k}; the PGNN regressor n_a={n_a}, n_b={n_b}, "
                             f"n_k={n_k}: make them equal")
        names = None if inverse else physics_model.param_names
        return LinearFeatures(n_a + n_b, names)
    if input_is_model_input and averaged and hasattr(physics_model, "with_direct_input"):
        physics_model = physics_model.with_direct_input()   # the data's input is already w = ū
    pa = getattr(physics_model, "n_a", None)      # a plant model reads φ in its own layout (e.g. [B1] (32):
    if not inverse and pa is not None:            # [y(t-1), y(t-2), w(t-1)]): the PGNN's must start with it
        pb, pk = int(getattr(physics_model, "n_b", 1)), int(getattr(physics_model, "n_k", 0))
        if (n_a, n_k) != (int(pa), pk) or n_b < pb:
            raise ValueError(f"{name} reads the regressor as [y(t-1) … y(t-{pa}), its input's {pb} lag(s)] with "
                             f"n_k = {pk}; the PGNN regressor has n_a={n_a}, n_b={n_b}, n_k={n_k}, so the physics "
                             f"would read an output lag as its input: set model.n_a={pa}, model.n_b>={pb}, "
                             f"model.n_k={pk}")
    return PhysicsModelFeatures(physics_model, inverse)
