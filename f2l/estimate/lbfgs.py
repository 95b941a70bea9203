"""The estimators' batched L-BFGS: all starts of a face optimised as one summed objective."""

from __future__ import annotations

import torch

from f2l.estimate.config import EstimatorConfig


def minimise(objective, variables, max_iter: int, tolerance_change: float, tolerance_grad: float = 1e-10,
             frozen: tuple[int, ...] = ()):
    """torch's L-BFGS (strong-Wolfe line search, history 20) on ``objective(*leaves)[0].sum()``,
    ``objective`` returning per-start (totals (B,), data terms (B,)) of the unconstrained
    ``variables``; the leaves at ``frozen`` positions are not trained. Returns the optimised
    leaves (detached) and the iterations taken. One line search serves every start."""
    leaves = [v.detach().clone().requires_grad_(True) for v in variables]
    trained = [leaf for i, leaf in enumerate(leaves) if i not in frozen]
    optimiser = torch.optim.LBFGS(
        trained, lr=1.0, max_iter=max_iter, tolerance_grad=tolerance_grad, tolerance_change=tolerance_change,
        history_size=20, line_search_fn="strong_wolfe",
    )

    def closure():
        optimiser.zero_grad()
        loss = objective(*leaves)[0].sum()
        loss.backward()
        return loss

    optimiser.step(closure)
    state = optimiser.state[optimiser._params[0]]
    return tuple(v.detach() for v in leaves), int(state.get("n_iter", 0))


def run_lbfgs(prob, unpack, variables, cfg: EstimatorConfig, max_iter: int):
    """:func:`minimise` on the objective of ``prob`` (:class:`f2l.estimate.problem.FaceProblem`)
    over the unconstrained (x_theta, x_gnd, x_rho), mapped to parameters by ``unpack``. Sun models
    stop on a change below ``cfg.tolerance`` x 1e-2 of the starting data term, the others on
    ``cfg.tolerance``; a fixed albedo (``cfg.fixed_albedo``) is not trained."""

    def objective(*leaves):
        return prob.objective(*unpack(*leaves))

    tolerance = cfg.tolerance
    if prob.hybrid is not None:  # relative to the objective: ~1e-2 of data term at the start
        with torch.no_grad():
            tolerance = cfg.tolerance * 1e-2 * float(objective(*variables)[1].sum())
    return minimise(objective, variables, max_iter, tolerance, frozen=() if cfg.fixed_albedo is None else (2,))
