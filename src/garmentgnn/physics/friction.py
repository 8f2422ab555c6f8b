"""Smoothed Coulomb friction as a lagged dissipative potential (IPC).

Li et al., "Incremental Potential Contact", ACM TOG 39(4), 2020, Sec. 5: over one
implicit step, a contact with (lagged) normal force ``lambda``, (lagged) unit normal
``n`` and tangential relative displacement ``u = (I - n n^T) (dx - dx_collider)`` adds

    ``D(u) = mu lambda f0(|u|)``,

    ``f0(y) = -y^3 / (3 eps^2) + y^2 / eps + eps / 3``  for ``y < eps``,  ``y`` otherwise,

whose gradient ``mu lambda f1(|u|) u / |u|`` (``f1 = f0'``, ``f1(y) = 2 y / eps - y^2 / eps^2``
below ``eps``, 1 above) is the Coulomb force of magnitude ``mu lambda`` opposing sliding,
smoothed into a stiff "creep" regime for ``|u| < eps`` (``eps = eps_v h``: sliding slower
than ``eps_v`` counts as static friction).  Because ``lambda`` and ``n`` are frozen over
the step (taken from the state at which the contacts were linearised) ``D`` is a potential
that Newton minimises with the other energies; it only ever removes energy
(``u . grad D >= 0``).  Used by :mod:`garmentgnn.sim` (and usable by losses).
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["friction_energy", "friction_hessian"]


def _tangential(displacement: Tensor, normal: Tensor) -> Tensor:
    return displacement - (displacement * normal).sum(-1, keepdim=True) * normal


def _check(mu: float, eps: float) -> None:
    if not mu >= 0:
        raise ValueError(f"`mu`: the friction coefficient must be >= 0, got {mu}")
    if not eps > 0:
        raise ValueError(f"`eps`: the static-friction displacement threshold must be > 0 (m), "
                         f"got {eps}")


def friction_energy(displacement: Tensor, normal: Tensor, normal_force: Tensor, mu: float,
                    eps: float, reduce: str = "sum") -> Tensor:
    """``sum_c mu lambda_c f0(|u_c|)`` (see the module docstring).

    Args:
        displacement: ``[..., C, 3]`` relative displacement of each contact over the step
            (cloth vertex displacement minus the collider's at the contact point).
        normal: ``[..., C, 3]`` unit contact normals (lagged).
        normal_force: ``[..., C]`` normal force magnitudes ``lambda >= 0`` (N, lagged).
        mu: Coulomb coefficient.
        eps: displacement below which friction is static (``eps_v * h``, m).
        reduce: ``"sum"`` or ``"none"`` (per contact).
    """
    _check(mu, eps)
    u = _tangential(displacement, normal)
    y = (u * u).sum(-1).clamp_min(1e-30).sqrt()
    f0 = (y < eps) * (-y ** 3 / (3 * eps * eps) + y * y / eps + eps / 3) + (y >= eps) * y
    e = mu * normal_force.to(u.dtype) * f0
    if reduce == "none":
        return e
    if reduce != "sum":
        raise ValueError(f"`reduce`: expected 'sum' or 'none', got {reduce!r}")
    return e.sum(-1)


def friction_hessian(displacement: Tensor, normal: Tensor, normal_force: Tensor, mu: float,
                     eps: float) -> Tensor:
    """``[C, 3, 3]`` Hessians of :func:`friction_energy` per contact, with respect to the
    displacement, made PSD as in IPC.

    With ``P = I - n n^T``, ``u = P d``, ``y = |u|``: the exact Hessian is
    ``mu lambda P (f1/y P + (f1' - f1/y) u u^T / y^2) P``.  Below ``eps`` it is PSD as
    is (``f1/y = 2/eps - y/eps^2`` and ``f1' = 2/eps - 2y/eps^2`` are both >= 0);
    above ``eps`` (``f1 = 1, f1' = 0``) it is ``mu lambda / y (P - u u^T / y^2)``, also
    PSD.  Both are returned exactly (tested against autograd).
    """
    _check(mu, eps)
    P = torch.eye(3, dtype=normal.dtype, device=normal.device) \
        - normal.unsqueeze(-1) * normal.unsqueeze(-2)
    u = _tangential(displacement, normal)
    y = (u * u).sum(-1).clamp_min(1e-30).sqrt()
    slow = y < eps
    a = (slow * (2 / eps - y / (eps * eps)) + ~slow / y)  # f1 / y
    b = (slow * (-1 / (eps * eps * y)) + ~slow * (-1 / y ** 3))  # (f1' - f1/y) / y^2
    uu = u.unsqueeze(-1) * u.unsqueeze(-2)
    k = (mu * normal_force.to(u.dtype)).unsqueeze(-1).unsqueeze(-1)
    return k * (a.unsqueeze(-1).unsqueeze(-1) * P + b.unsqueeze(-1).unsqueeze(-1) * uu)

