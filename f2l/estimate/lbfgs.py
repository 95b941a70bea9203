"""The estimators' batched L-BFGS: all starts of a face optimised as one summed objective."""

from __future__ import annotations

import sys

import torch

from f2l.estimate.config import EstimatorConfig


def _without_dynamo_import() -> None:
    """torch.optim wraps its optimisers' methods in ``torch._disable_dynamo``, whose wrapper imports
    ``torch._dynamo`` (about 1 s, most of a cold ``f2l estimate`` past torch itself) on the first
    call only to mark the method as not to be compiled. f2l never compiles, so while
    ``torch._dynamo`` is not loaded, each such wrapped method of ``torch.optim.LBFGS`` is marked
    with itself as its "disabled" form, which is what the wrapper caches after that import. Once
    anything has imported ``torch._dynamo``, torch's own path is left alone."""
    if "torch._dynamo" in sys.modules:
        return
    import torch._compile

    wrapper_file = torch._compile.__file__
    for cls in torch.optim.LBFGS.__mro__:
        for attr in vars(cls).values():
            fn = getattr(attr, "__wrapped__", None)
            code = getattr(attr, "__code__", None)
            if fn is not None and code is not None and code.co_filename == wrapper_file \
                    and not hasattr(fn, "__dynamo_disable"):
                fn.__dynamo_disable = fn


def minimise(objective, variables, max_iter: int, tolerance_change: float, tolerance_grad: float = 1e-10,
             frozen: tuple[int, ...] = ()):
    """torch's L-BFGS (strong-Wolfe line search, history 20) on ``objective(*leaves)[0].sum()``,
    ``objective`` returning per-start (totals (B,), data terms (B,)) of the unconstrained
    ``variables``; the leaves at ``frozen`` positions are not trained. Returns the optimised
    leaves (detached) and the iterations taken. One line search serves every start."""
    _without_dynamo_import()
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
