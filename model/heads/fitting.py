"""The training loop the fine-tuning stages and the member path head share: some of a network's
parameters fitted in shuffled batches, the epoch with the lowest validation loss kept."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch


def fit_best(
    net: torch.nn.Module,
    keep: torch.nn.Module,
    n: int,
    batch_loss: Callable[[torch.Tensor], torch.Tensor],
    val_loss: Callable[[], float],
    epochs: int,
    lr: float,
    batch_size: int,
    seed: int,
    log: Callable[[str], None] | None,
    label: str = "",
    min_batch: int = 1,
) -> tuple[int, list[dict]]:
    """Train ``keep``'s parameters (the rest of ``net`` frozen) on ``n`` examples in shuffled batches,
    Adam with cosine decay to 1% of ``lr``; ``keep`` is restored to the epoch with the lowest
    ``val_loss`` (the untrained start counts as epoch -1). ``batch_loss`` takes a batch's example
    indices; batches under ``min_batch`` examples are skipped.

    Returns the best epoch and the per-epoch history (train and validation loss).
    """
    params = list(keep.parameters())
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr)
    steps = math.ceil(n / batch_size)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * steps, eta_min=lr * 0.01)
    gen = torch.Generator().manual_seed(seed)
    best, best_state, best_epoch = val_loss(), None, -1
    history = []
    for epoch in range(epochs):
        net.train()
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(steps):
            idx = perm[i * batch_size : (i + 1) * batch_size]
            if len(idx) < min_batch:
                continue
            loss = batch_loss(idx)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() / steps
        v = val_loss()
        history.append({"epoch": epoch, "train_loss": total, "val_loss": v})
        if log:
            log(f"  {label}epoch {epoch}: train loss {total:.4f}, val loss {v:.4f}")
        if v < best:
            best, best_epoch = v, epoch
            best_state = {k: t.detach().clone() for k, t in keep.state_dict().items()}
    if best_state is not None:
        keep.load_state_dict(best_state)
    for p in params:
        p.requires_grad_(False)
    net.eval()
    return best_epoch, history
