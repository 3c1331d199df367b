"""Robust PLR, PLR-perp (Jiang et al. 2021b): PLR without gradient updates on fresh levels,
which are only scored (by Explorers on the Ray driver); that is what makes its regret-based
curriculum a minimax-regret strategy."""

from __future__ import annotations

from ued.curricula.plr import PLR


class RobustPLR(PLR):
    """PLR whose fresh levels are scored, not trained on (unless asked for)."""

    name = "robust_plr"
    default_exploratory_grad_updates = False


__all__ = ["RobustPLR"]
