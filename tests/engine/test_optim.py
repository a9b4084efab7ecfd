"""The optimisers: the fused Adam the trainer uses against torch's reference loop, through densification edits."""

import torch
from torch import nn

from metegs.densify.surgery import append_rows, select_rows
from metegs.engine.optim import adam


def _params(seed: int) -> nn.ParameterDict:
    g = torch.Generator().manual_seed(seed)
    return nn.ParameterDict(
        {
            "means": nn.Parameter(torch.randn(50, 3, generator=g)),
            "shN": nn.Parameter(torch.randn(50, 15, 3, generator=g)),
        }
    )


def _grads(params: nn.ParameterDict, step: int) -> None:
    g = torch.Generator().manual_seed(1000 + step)
    for p in params.values():
        p.grad = torch.randn(p.shape, generator=g)


def test_adam_is_fused_on_cpu_where_torch_has_it():
    opt = adam([nn.Parameter(torch.zeros(3))], lr=1e-3)
    has_fused_cpu = tuple(int(v) for v in torch.__version__.split(".")[:2]) >= (2, 4)
    assert opt.defaults["fused"] is (True if has_fused_cpu else None)


def test_fused_adam_matches_the_reference_through_row_edits():
    fast, ref = _params(0), _params(0)
    lrs = {"means": 1e-2, "shN": 1e-3}
    fast_opt = {k: adam([fast[k]], lr=lr, eps=1e-15) for k, lr in lrs.items()}
    ref_opt = {k: torch.optim.Adam([ref[k]], lr=lr, eps=1e-15, foreach=False) for k, lr in lrs.items()}
    keep = torch.arange(50) % 3 != 0
    new = {"means": torch.ones(7, 3), "shN": torch.zeros(7, 15, 3)}
    for step in range(12):
        for params, opts in ((fast, fast_opt), (ref, ref_opt)):
            _grads(params, step)
            for o in opts.values():
                o.step()
                o.zero_grad(set_to_none=True)
            if step == 4:
                select_rows(params, opts, keep)
            if step == 8:
                append_rows(params, opts, new)
    for k in lrs:
        assert fast[k].shape == ref[k].shape
        torch.testing.assert_close(fast[k].data, ref[k].data, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(
            fast_opt[k].state[fast[k]]["exp_avg_sq"], ref_opt[k].state[ref[k]]["exp_avg_sq"], rtol=1e-5, atol=1e-8
        )
