"""A small recurrent gate over stem features (issue 37 item 3 (c)): a gate with memory that learns it.

Hysteresis and an exponential average (`fusion.temporal`) give a per-frame gate memory by a fixed
rule. This gate learns what to carry from frame to frame: per frame it reads each stem channel's
mean over the pooled grid (the deep gate's `pooling: global` input, 64 values per sensor, from
`fusion.nets.branch_gates.pool_features`), standardised with the fitting frames' mean and standard
deviation; a GRU runs over the frames of a sequence; a linear head gives one predicted loss per
branch, `target_center + target_scale * head(h_t)`, the head starting at zero so that the untrained
gate predicts the per-branch median loss of the fitting frames (as `ConvGate`). Lower is better, as
for every gate; the choice is argmin per frame.

It is trained on sequences (`fit_recurrent`): mean absolute error of the scaled prediction against
each frame's per-branch losses (the deep gate's "mae" objective, HydraFusion 5.2.2), Adam, whole
sequences per batch; the epoch kept is the one of lowest top-1 regret on the validation sequences
(ties: lower validation MAE, then the earlier epoch; without validation sequences, the last).

Sequences it is run on may be longer than those it learned from: `predict_sequence` runs it either
over the whole sequence from a zero state (`window=None`), or, per frame t, over the last `window`
frames only (t - window + 1 .. t, from a zero state each time): the memory it was trained to use,
never more. Which window a study uses is chosen on validation sequences.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn


def channel_means(pooled) -> np.ndarray:
    """(N, C, rows, cols) pooled stem features (float16 or float32) -> (N, C) float32: each channel's
    mean over the grid (what the recurrent gate reads per frame)."""
    x = np.asarray(pooled)
    if x.ndim != 4:
        raise ValueError(f"pooled: expected (N, C, rows, cols), got shape {x.shape}")
    return x.astype(np.float32).mean(axis=(2, 3))


class RecurrentGate(nn.Module):
    """GRU gate: (B, T, inputs) per-frame features -> (B, T, branches) predicted losses.

    Args:
        inputs: per-frame feature width (64 per sensor read).
        branches: number of predicted losses (one per branch).
        hidden: GRU state width.
        dropout: on the standardised input during training.
    """

    def __init__(self, inputs: int, branches: int, hidden: int = 32, dropout: float = 0.1) -> None:
        super().__init__()
        if inputs < 1 or branches < 1 or hidden < 1:
            raise ValueError(f"inputs, branches and hidden must be >= 1, got {inputs}, {branches}, {hidden}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout: must be in [0, 1), got {dropout}")
        self.options = {"inputs": int(inputs), "branches": int(branches), "hidden": int(hidden),
                        "dropout": float(dropout)}
        self.drop = nn.Dropout(dropout)
        self.gru = nn.GRU(inputs, hidden, batch_first=True)
        self.head = nn.Linear(hidden, branches)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.register_buffer("input_mean", torch.zeros(inputs))
        self.register_buffer("input_std", torch.ones(inputs))
        self.register_buffer("target_center", torch.zeros(branches))
        self.register_buffer("target_scale", torch.ones(branches))

    def forward(self, x: Tensor, h: Tensor | None = None) -> tuple[Tensor, Tensor]:
        n = self.input_mean.numel()
        if x.dim() != 3 or x.shape[-1] != n:
            raise ValueError(f"x: expected (B, T, {n}), got shape {tuple(x.shape)}")
        z = (x.float() - self.input_mean) / self.input_std
        out, h = self.gru(self.drop(z), h)
        return self.target_center + self.target_scale * self.head(out), h

    @torch.no_grad()
    def fit_normalization(self, x, losses) -> None:
        """Input standardisation from fitting frames x (N, inputs); output centre and scale from their
        losses (N, branches): median and mean absolute deviation (as `ConvGate.fit_normalization`)."""
        x = torch.as_tensor(np.asarray(x), dtype=torch.float32)
        y = torch.as_tensor(np.asarray(losses), dtype=torch.float32)
        self.input_mean.copy_(x.mean(dim=0))
        self.input_std.copy_(x.std(dim=0, unbiased=False).clamp_min(1e-3))
        center = torch.quantile(y, 0.5, dim=0)
        self.target_center.copy_(center)
        self.target_scale.copy_((y - center).abs().mean(dim=0).clamp_min(1e-3))

    @torch.no_grad()
    def predict_sequence(self, x, window: int | None = None) -> np.ndarray:
        """One sequence's features (T, inputs) in time order -> (T, branches) predicted losses: the GRU
        over the whole sequence (`window` None), or frame t from frames t - window + 1 .. t only."""
        was = self.training
        self.eval()
        try:
            x = torch.as_tensor(np.asarray(x), dtype=torch.float32)
            if x.dim() != 2 or not len(x):
                raise ValueError(f"x: expected a non-empty (T, inputs) sequence, got shape {tuple(x.shape)}")
            if window is None:
                return self(x[None])[0][0].numpy()
            if int(window) < 1:
                raise ValueError(f"window: must be >= 1 or None, got {window!r}")
            w = int(window)
            t = len(x)
            idx = torch.arange(t)[:, None] - (w - 1) + torch.arange(w)[None, :]  # (T, w), frames t-w+1..t
            valid = idx >= 0
            # frames before the sequence's start: run from the first real frame (left-padded windows
            # are cut by running each distinct start length apart)
            out = np.empty((t, self.head.out_features), dtype=np.float32)
            first = valid.float().argmax(dim=1)  # index of the first real frame in each window
            for f in torch.unique(first).tolist():
                rows = torch.nonzero(first == f).flatten()
                seqs = x[idx[rows, f:]]  # (r, w - f, inputs)
                out[rows.numpy()] = self(seqs)[0][:, -1].numpy()
            return out
        finally:
            self.train(was)


def _stack(sequences: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[tuple[Tensor, Tensor]]:
    """Group (x (T, F), y (T, n)) sequences by length into batches-to-be of equal T."""
    by_len: dict[int, list] = {}
    for x, y in sequences:
        if len(x) != len(y) or not len(x):
            raise ValueError("each sequence: features and losses of the same non-zero length")
        by_len.setdefault(len(x), []).append((x, y))
    return [(torch.as_tensor(np.stack([a for a, _ in v]), dtype=torch.float32),
             torch.as_tensor(np.stack([b for _, b in v]), dtype=torch.float32)) for _, v in sorted(by_len.items())]


@torch.no_grad()
def evaluate(gate: RecurrentGate, sequences: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict:
    """Mean over frames of the top-1 regret (loss of the argmin branch minus the frame's lowest) and
    of the absolute error, the GRU run over each whole sequence."""
    gate.eval()
    regret, err, n = 0.0, 0.0, 0
    for x, y in _stack(sequences):
        p = gate(x)[0]
        pick = p.argmin(dim=-1, keepdim=True)
        regret += float((y.gather(-1, pick).squeeze(-1) - y.min(dim=-1).values).sum())
        err += float((p - y).abs().mean(dim=-1).sum())
        n += y.shape[0] * y.shape[1]
    return {"regret": regret / n, "mae": err / n}


def fit_recurrent(gate: RecurrentGate, fit: Sequence[tuple[np.ndarray, np.ndarray]],
                  val: Sequence[tuple[np.ndarray, np.ndarray]], epochs: int = 60, lr: float = 1e-3,
                  batch_size: int = 32, weight_decay: float = 1e-4, seed: int = 0, progress=None) -> dict:
    """Train `gate` on the fitting sequences [(features (T, F), losses (T, n))], keep the epoch of lowest
    validation regret (module doc; without validation sequences, the last epoch: nothing to choose
    on). Normalisation is set from the fitting frames first. Returns the history (one row per epoch)
    and the kept epoch; the gate holds the kept epoch's weights. `progress(epoch, row)`: called after
    each epoch."""
    if epochs < 1:
        raise ValueError(f"epochs: must be >= 1, got {epochs}")
    if not fit:
        raise ValueError("fit_recurrent: needs fitting sequences")
    gate.fit_normalization(np.concatenate([x for x, _ in fit]), np.concatenate([y for _, y in fit]))
    groups = _stack(fit)
    gen = torch.Generator().manual_seed(int(seed))
    torch.manual_seed(int(seed))
    opt = torch.optim.Adam(gate.parameters(), lr=lr, weight_decay=weight_decay)
    history, best, best_key = [], None, (math.inf, math.inf)
    def scored(epoch, train_mae):
        v = evaluate(gate, val) if val else {"regret": None, "mae": None}
        row = {"epoch": epoch, "train_mae": train_mae,
               "val_regret": None if v["regret"] is None else round(v["regret"], 6),
               "val_mae": None if v["mae"] is None else round(v["mae"], 6)}
        history.append(row)
        # without validation, each epoch replaces the one before (the last is kept)
        return row, ((v["regret"], v["mae"]) if val else (-float(epoch), 0.0))

    _row, best_key = scored(0, None)
    best, best_epoch = copy.deepcopy(gate.state_dict()), 0
    for epoch in range(1, epochs + 1):
        gate.train()
        total, count = 0.0, 0
        batches = [(g, b) for g, (x, _) in enumerate(groups)
                   for b in torch.randperm(len(x), generator=gen).split(batch_size)]
        order = torch.randperm(len(batches), generator=gen).tolist()
        for i in order:
            g, rows = batches[i]
            x, y = groups[g][0][rows], groups[g][1][rows]
            p = gate(x)[0]
            loss = ((p - y).abs() / gate.target_scale).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(rows)
            count += len(rows)
        row, key = scored(epoch, round(total / count, 6))
        if key < best_key:
            best, best_key, best_epoch = copy.deepcopy(gate.state_dict()), key, epoch
        if progress is not None:
            progress(epoch, row)
    gate.load_state_dict(best)
    gate.eval()
    kept = history[best_epoch]
    return {"history": history, "best_epoch": best_epoch, "val_regret": kept["val_regret"],
            "val_mae": kept["val_mae"], "kept_by": "validation regret" if val else "last epoch (no validation)"}
