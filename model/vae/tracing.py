"""One-z_B decoding as a frozen TorchScript graph (the designer's slider path)."""

from __future__ import annotations

import torch
from torch import nn

from snakeloco.model.vae.network import HierarchicalVAE


class _Method(nn.Module):
    def __init__(self, net: HierarchicalVAE, method: str) -> None:
        super().__init__()
        self.net, self.method = net, method

    def forward(self, z_b: torch.Tensor, z_j: torch.Tensor):
        return getattr(self.net, self.method)(z_b, z_j)


def trace_single(net: HierarchicalVAE, method: str = "generate") -> torch.jit.ScriptModule:
    """``net.<method>(z_b (1, Db), z_j (1, K, Dj))`` as a frozen TorchScript graph, for one z_B:
    ``generate`` or ``generate_shape`` (z_j: the joint latents) or ``sample_joints`` (z_j: the
    prior's noise).

    Why: eager PyTorch releases and re-takes the GIL around each of the few hundred small ops of a
    decode, so in a server where any other Python thread is busy (another tab drawing, the websocket
    loop) each re-take waits up to the interpreter's switch interval. Measured against one busy
    Python thread: eager p50 1409 ms, traced 19.7 ms (alone: 5.3 vs 3.5 ms); outputs are
    bit-identical (tested). torch.jit is deprecated in favour of torch.export, which needs a
    compiler toolchain at run time; the pinned torch range still has it.
    """
    import warnings

    zb = torch.zeros(1, net.cfg.z_b_dim)
    zj = torch.zeros(1, net.cfg.n_joints, net.cfg.z_j_dim)
    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the deprecation notice, and the constant signal_ready check
        return torch.jit.freeze(torch.jit.trace(_Method(net, method).eval(), (zb, zj), check_trace=False))


class _OneArg(nn.Module):
    def __init__(self, module: nn.Module, method: str) -> None:
        super().__init__()
        self.module, self.method = module, method

    def forward(self, x: torch.Tensor):
        return getattr(self.module, self.method)(x)


def trace_one_arg(module: nn.Module, method: str, example: torch.Tensor) -> torch.jit.ScriptModule:
    """``module.<method>(x)`` for inputs shaped like ``example`` as a frozen TorchScript graph (the
    member path head and the statistics head on one decoded member: the same GIL reasons as
    ``trace_single``)."""
    import warnings

    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.freeze(
            torch.jit.trace(_OneArg(module, method).eval(), (example,), check_trace=False)
        )


class Graphs:
    """A network's traced graphs, each made on first use and kept (None where this torch cannot
    trace it: then the eager call gives the same numbers)."""

    def __init__(self, net: HierarchicalVAE) -> None:
        self.net = net
        self.made: dict[str, torch.jit.ScriptModule | None] = {}

    def _get(self, name: str, make):
        if name not in self.made:
            try:
                self.made[name] = make()
            except Exception:
                self.made[name] = None
        return self.made[name]

    def single(self, method: str):
        """The one-z_B graph of ``net.<method>`` (``trace_single``)."""
        return self._get(method, lambda: trace_single(self.net, method))

    def one_input(self, name: str, module: nn.Module, method: str, example: torch.Tensor):
        """The graph of ``module.<method>`` for inputs shaped like ``example`` (``trace_one_arg``)."""
        return self._get(name, lambda: trace_one_arg(module, method, example))
