"""HydraFusion: shared stems, selectable early-fusion branches, batched selective execution.

`HydraFusion(stems, branches, gate, fusion_block, transform=...)` is a torchvision-style skeleton
(`GeneralizedRCNN(backbone, rpn, roi_heads, transform)`): named slots, branches in an
`nn.ModuleDict` keyed by name. `build_hydrafusion(profile=..., branches=..., **overrides)` builds
one from a model profile (`configs/model/<profile>.yaml`).

Selective execution (HydraFusion Algorithm 1, EcoFusion Algorithm 1): each sample selects a set of
branches (an EcoFusion *configuration*). A forward pass runs only the stems those branches need,
each stem once on the samples that need it, and each selected branch once on the group of samples
that selected it; results are scattered back to sample order.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from fusion.nets.layers import Branch, Stem, build_branch, build_stem
from fusion.nets.profile import FRAMES, SENSORS, BranchSpec, ModelProfile, SensorNorm, load_profile

LOSS_NAMES = ("loss_classifier", "loss_box_reg", "loss_objectness", "loss_rpn_box_reg")
"""torchvision's Faster R-CNN losses, the keys of every per-branch loss dict."""


class SensorTransform(nn.Module):
    """Checks, normalises and pads sensor tensors (torchvision's GeneralizedRCNNTransform minus resizing).

    Args:
        normalization: sensor name -> SensorNorm (per-channel mean and std).
        sizes: view name ("camera", "bev") -> (H, W) every input of that view must have.
        strides: view name -> output stride; inputs are zero-padded at the bottom and right, after
            normalisation, to a multiple of it so anchor strides are exact.

    `forward(sensor, x)`: x (N, C, H, W) float -> (N, C, H_pad, W_pad) normalised and padded.
    """

    def __init__(
        self,
        *,
        normalization: Mapping[str, SensorNorm],
        sizes: Mapping[str, tuple[int, int]],
        strides: Mapping[str, int],
    ) -> None:
        super().__init__()
        self.sizes = {v: (int(s[0]), int(s[1])) for v, s in sizes.items()}
        self.strides = {v: int(s) for v, s in strides.items()}
        self.sensors = tuple(normalization)
        for sensor, norm in normalization.items():
            self.register_buffer(
                f"mean_{sensor}", torch.tensor(norm.mean, dtype=torch.float32).view(1, -1, 1, 1)
            )
            self.register_buffer(
                f"std_{sensor}", torch.tensor(norm.std, dtype=torch.float32).view(1, -1, 1, 1)
            )

    def image_size(self, sensor: str) -> tuple[int, int]:
        return self.sizes[SENSORS[sensor].view]

    def padded_size(self, sensor: str) -> tuple[int, int]:
        (h, w), s = self.image_size(sensor), self.strides[SENSORS[sensor].view]
        return (-(-h // s) * s, -(-w // s) * s)

    def check(self, sensor: str, x: Any) -> int:
        """Validate one input tensor; returns its batch size. Errors name `inputs[sensor]`."""
        field = f"inputs[{sensor!r}]"
        if not isinstance(x, Tensor):
            raise ValueError(f"{field}: expected a torch.Tensor, got {type(x).__name__}")
        if x.dtype != torch.float32:
            raise ValueError(f"{field}: expected a float32 tensor (values about 0..1), got {x.dtype}")
        c = SENSORS[sensor].channels
        h, w = self.image_size(sensor)
        if x.dim() != 4 or tuple(x.shape[1:]) != (c, h, w) or x.shape[0] < 1:
            raise ValueError(f"{field}: expected shape (B, {c}, {h}, {w}) with B >= 1, got {tuple(x.shape)}")
        return int(x.shape[0])

    def forward(self, sensor: str, x: Tensor) -> Tensor:
        x = (x - getattr(self, f"mean_{sensor}")) / getattr(self, f"std_{sensor}")
        (h, w), (hp, wp) = self.image_size(sensor), self.padded_size(sensor)
        if (hp, wp) != (h, w):
            x = nn.functional.pad(x, (0, wp - w, 0, hp - h))
        return x


class HydraFusion(nn.Module):
    """Context-aware selective sensor fusion network (HydraFusion, ICCPS 2022; EcoFusion, DAC 2022).

    Args:
        stems: modality name ("camera", "radar", "lidar", "fwd_lidar") -> Stem. One stem per
            modality, shared by that modality's sensors (camera_left and camera_right share "camera").
        branches: branch name -> Branch, in a fixed order (the order of every output dict).
        gate: optional module called as `gate(features, meta)` with `features` as returned by
            `extract_features` (every sensor present in the inputs) and `meta` as given to
            `forward`; it returns a selection (see `forward`). Used when `forward` gets no selection.
            A gate whose `reads` attribute is not "features" (the knowledge gate: external context)
            is called with features None before any stem runs, and only the stems its selection
            needs run. None: no gate, a missing selection means all branches.
        fusion_block: optional module called in eval mode as
            `fusion_block(detections, branch_frames, meta)` with `detections` the per-sample,
            per-branch detections described under `forward`; its result is returned instead of
            them. None: `forward` returns the per-branch detections. Not used in training mode.
        transform: SensorTransform (input checks, per-sensor normalisation, padding).

    Attributes:
        profile: the ModelProfile `build_hydrafusion` built it from (None when built by hand).

    `forward(inputs, targets=None, selection=None, meta=None)`:
        inputs: dict sensor name -> float32 tensor (B, C, H, W), values about 0..1, any subset of
            "camera_left", "camera_right" (B, 3, Hc, Wc), "fwd_lidar" (B, 3, Hc, Wc),
            "radar" (B, 1, Hb, Wb), "lidar" (B, 3, Hb, Wb); (Hc, Wc) and (Hb, Wb) are the profile's
            camera and bev sizes. Only the sensors of the selected branches must be present.
        targets: training mode only: a list of B dicts frame name ("camera_left", "camera_right",
            "bev") -> {"boxes": (N, 4) float x1, y1, x2, y2 in that frame's pixels,
            "labels": (N,) int64 in 1..num_classes-1}; each sample needs the frames of its branches.
        selection: None (the gate's choice if there is a gate, else every branch), a list of branch
            names run on every sample, or a list of B such lists (one per sample).
        meta: optional list of B per-sample objects (e.g. calibration, external context), handed
            to the gate and the fusion block unchanged.
        Returns, training mode: {"total": scalar, "branches": {name: {four losses}}} where each
            branch's losses are torchvision's four Faster R-CNN losses averaged over the samples that
            selected it, and total = sum over branches of (n_branch / B) * sum of its four losses
            (with one shared selection: the plain sum, as torchvision). Eval mode: a list of B dicts
            branch name -> {"boxes": (D, 4) float in the branch's frame, clipped to the image,
            "labels": (D,) int64, "scores": (D,) float}, holding the sample's selected branches in
            branch order (or the fusion block's output).

    Raises:
        ValueError naming the field: unknown sensor keys, wrong dtype/shape/size, a sensor missing
            for a selected branch, unknown or repeated branch names, bad targets.
    """

    def __init__(
        self,
        stems: Mapping[str, Stem],
        branches: Mapping[str, Branch],
        gate: nn.Module | None = None,
        fusion_block: nn.Module | None = None,
        *,
        transform: SensorTransform,
    ) -> None:
        super().__init__()
        if not branches:
            raise ValueError("branches: a HydraFusion network needs at least one branch")
        self.stems = nn.ModuleDict(stems)
        self.branches = nn.ModuleDict(branches)
        for name, branch in self.branches.items():
            if getattr(branch, "name", name) != name:
                raise ValueError(f"branches: key {name!r} holds branch {branch.name!r}")
            for s in branch.sensors:
                if s not in SENSORS:
                    raise ValueError(f"branches: branch {name!r} needs unknown sensor {s!r}")
                if getattr(branch, "fusion", "features") == "features" and SENSORS[s].stem not in self.stems:
                    raise ValueError(
                        f"stems: branch {name!r} needs stem {SENSORS[s].stem!r} for sensor {s!r}"
                    )
                if s not in transform.sensors:
                    raise ValueError(f"transform: no normalisation for sensor {s!r} of branch {name!r}")
        self.gate = gate
        self.fusion_block = fusion_block
        self.transform = transform
        self.profile: ModelProfile | None = None

    # ----- what the network is made of -------------------------------------------------------

    @property
    def branch_sensors(self) -> dict[str, tuple[str, ...]]:
        """Branch name -> the sensors it consumes, in the order their features are concatenated."""
        return {name: tuple(b.sensors) for name, b in self.branches.items()}

    @property
    def branch_frames(self) -> dict[str, str]:
        """Branch name -> the frame its boxes are in ("camera_left", "camera_right" or "bev")."""
        return {name: b.frame for name, b in self.branches.items()}

    @property
    def sensors(self) -> tuple[str, ...]:
        """Every sensor some branch consumes, in `SENSORS` order."""
        used = {s for b in self.branches.values() for s in b.sensors}
        return tuple(s for s in SENSORS if s in used)

    def expand_selection(self, selection: Any, batch_size: int) -> list[tuple[str, ...]]:
        """Normalise a selection to one tuple of branch names per sample, in branch order.

        `selection`: None (every branch), a list of names (every sample), or a list of
        `batch_size` lists of names. Raises ValueError for unknown, repeated or no names.
        """
        names = list(self.branches)
        if selection is None:
            return [tuple(names)] * batch_size
        if isinstance(selection, str) or not isinstance(selection, Sequence) or len(selection) == 0:
            raise ValueError(
                "selection: expected a non-empty list of branch names or a list of per-sample lists, "
                f"got {selection!r}"
            )
        if all(isinstance(s, str) for s in selection):
            selection = [selection] * batch_size
            fields = ["selection"] * batch_size
        elif all(isinstance(s, Sequence) and not isinstance(s, str) for s in selection):
            if len(selection) != batch_size:
                raise ValueError(f"selection: {len(selection)} per-sample lists for a batch of {batch_size}")
            selection = list(selection)
            fields = [f"selection[{i}]" for i in range(batch_size)]
        else:
            raise ValueError(f"selection: mixes branch names and per-sample lists: {selection!r}")
        out = []
        for field, sample_selection in zip(fields, selection):
            if len(sample_selection) == 0:
                raise ValueError(f"{field}: no branch selected")
            for n in sample_selection:
                if not isinstance(n, str) or n not in self.branches:
                    raise ValueError(f"{field}: unknown branch {n!r} (branches: {', '.join(names)})")
            if len(set(sample_selection)) != len(sample_selection):
                raise ValueError(f"{field}: a branch is named twice in {list(sample_selection)}")
            out.append(tuple(n for n in names if n in sample_selection))
        return out

    def sensors_for(self, selection: Any = None) -> tuple[str, ...]:
        """Sensors the selected branches consume (any sample), in `SENSORS` order."""
        selection = self.expand_selection(selection, _batch_of(selection))
        used = {s for sample_selection in selection for n in sample_selection for s in self.branches[n].sensors}
        return tuple(s for s in SENSORS if s in used)

    def stems_for(self, selection: Any = None) -> tuple[str, ...]:
        """Shared stems the selected branches need (any sample), in `stems` order (branches that fuse
        their inputs, fusion "input", bring their own stem)."""
        selection = self.expand_selection(selection, _batch_of(selection))
        used = {SENSORS[s].stem for sample_selection in selection for n in sample_selection
                if self.branches[n].fusion == "features" for s in self.branches[n].sensors}
        return tuple(k for k in self.stems if k in used)

    # ----- stems -----------------------------------------------------------------------------

    def _check_inputs(self, inputs: Any) -> int:
        if not isinstance(inputs, Mapping):
            raise ValueError(f"inputs: expected a dict sensor name -> tensor, got {type(inputs).__name__}")
        if not inputs:
            raise ValueError("inputs: no sensor tensors given")
        batch = None
        for sensor, x in inputs.items():
            if sensor not in SENSORS:
                raise ValueError(f"inputs: unknown sensor {sensor!r} (known: {', '.join(SENSORS)})")
            if sensor not in self.transform.sensors:
                continue
            b = self.transform.check(sensor, x)
            if batch is None:
                batch = b
            elif b != batch:
                raise ValueError(
                    f"inputs[{sensor!r}]: batch size {b} differs from the other sensors' {batch}"
                )
        if batch is None:
            raise ValueError(f"inputs: none of this network's sensors ({', '.join(self.sensors)}) is present")
        return batch

    def _run_stems(
        self,
        inputs: Mapping[str, Tensor],
        needs: Mapping[str, list[int]],
        batch: int,
    ) -> dict[str, tuple[Tensor, dict[int, int]]]:
        """Run each needed stem once on the (sensor, samples) pairs that need it.

        Returns sensor -> (features of the needed samples, sample index -> row).
        """
        out: dict[str, tuple[Tensor, dict[int, int]]] = {}
        for stem_name, stem in self.stems.items():
            parts = [(s, idx) for s, idx in needs.items() if idx and SENSORS[s].stem == stem_name]
            if not parts:
                continue
            parts.sort(key=lambda p: list(SENSORS).index(p[0]))
            xs = []
            for sensor, idx in parts:
                x = inputs[sensor]
                if len(idx) != batch:
                    x = x.index_select(0, torch.as_tensor(idx, device=x.device))
                xs.append(self.transform(sensor, x))
            feats = stem(torch.cat(xs) if len(xs) > 1 else xs[0])
            for (sensor, idx), f in zip(parts, feats.split([len(i) for _, i in parts])):
                out[sensor] = (f, {i: r for r, i in enumerate(idx)})
        return out

    def stem_sensors(self, inputs: Mapping[str, Tensor]) -> list[str]:
        """The sensors whose stem features every branch together needs (`detect_and_losses`), in
        this network's sensor order."""
        _, needs = self._plan(inputs, self.expand_selection(None, self._check_inputs(inputs)))
        return [s for s in self.sensors if s in needs]

    def extract_features(
        self, inputs: Mapping[str, Tensor], sensors: Sequence[str] | None = None
    ) -> dict[str, Tensor]:
        """Stem features of every sample: sensor name -> (B, 64, H_pad/4, W_pad/4).

        `sensors`: which ones (all must be present); None: every sensor of this network present
        in `inputs`. Each stem runs once (camera_left and camera_right go through the camera stem
        together). This is what a gate consumes.
        """
        batch = self._check_inputs(inputs)
        if sensors is None:
            sensors = [s for s in self.sensors if s in inputs]
        for s in sensors:
            if s not in self.transform.sensors or SENSORS[s].stem not in self.stems:
                raise ValueError(f"sensors: this network has no stem for sensor {s!r}")
            if s not in inputs:
                raise ValueError(f"inputs: sensor {s!r} is missing")
        feats = self._run_stems(inputs, {s: list(range(batch)) for s in sensors}, batch)
        return {s: feats[s][0] for s in sensors}

    # ----- branches --------------------------------------------------------------------------

    def _plan(self, inputs: Mapping[str, Tensor], selection: list[tuple[str, ...]]):
        """Group samples by branch and list the samples each sensor is needed for."""
        groups = {n: [i for i, sample_selection in enumerate(selection) if n in sample_selection]
                  for n in self.branches}
        groups = {n: idx for n, idx in groups.items() if idx}
        needs: dict[str, set[int]] = {}
        for name, idx in groups.items():
            for s in self.branches[name].sensors:
                if s not in inputs:
                    raise ValueError(
                        f"inputs: sensor {s!r} is missing; branch {name!r} needs it for sample(s) {idx}"
                    )
                if self.branches[name].fusion == "features":  # input-fused branches have their own stem
                    needs.setdefault(s, set()).update(idx)
        return groups, {s: sorted(v) for s, v in needs.items()}

    def _check_targets(self, targets: Any, selection: list[tuple[str, ...]], values: bool | None = None) -> None:
        batch = len(selection)
        if not isinstance(targets, Sequence) or isinstance(targets, str | Mapping):
            raise ValueError(
                f"targets: expected a list of {batch} dicts frame -> boxes/labels, got {type(targets).__name__}"
            )
        if len(targets) != batch:
            raise ValueError(f"targets: {len(targets)} entries for a batch of {batch}")
        num_classes = self.branches[selection[0][0]].roi_heads.box_predictor.cls_score.out_features
        for i, (t, sample_selection) in enumerate(zip(targets, selection)):
            if not isinstance(t, Mapping):
                raise ValueError(
                    f"targets[{i}]: expected a dict frame name -> boxes/labels, got {type(t).__name__}"
                )
            for frame in t:
                if frame not in FRAMES:
                    raise ValueError(f"targets[{i}]: unknown frame {frame!r} (frames: {', '.join(FRAMES)})")
            for name in sample_selection:
                frame = self.branches[name].frame
                if frame not in t:
                    raise ValueError(f"targets[{i}]: no {frame!r} entry, needed by branch {name!r}")
            for frame in {self.branches[n].frame for n in sample_selection}:
                self._check_target(f"targets[{i}][{frame!r}]", t[frame], frame, num_classes, values)

    def check_targets(self, targets: Any, selection: Any = None) -> None:
        """Check training targets (as `forward` describes them) for the branches `selection` picks
        (None: every branch), values included; ValueError naming the field. `forward` checks the
        values of targets on the CPU itself; on a GPU each such check would wait for the device
        (about a hundred waits a step), so there it checks shapes and dtypes only, and a training
        loop calls this on the CPU before moving the targets."""
        batch = len(targets) if isinstance(targets, Sequence) and not isinstance(targets, str) else 1
        self._check_targets(targets, self.expand_selection(selection, batch), values=True)

    def _check_target(self, field: str, t: Any, frame: str, num_classes: int, values: bool | None = None) -> None:
        if not isinstance(t, Mapping) or "boxes" not in t or "labels" not in t:
            raise ValueError(f"{field}: expected a dict with 'boxes' and 'labels'")
        boxes, labels = t["boxes"], t["labels"]
        if (
            not isinstance(boxes, Tensor)
            or boxes.dtype != torch.float32
            or boxes.dim() != 2
            or boxes.shape[1] != 4
        ):
            raise ValueError(f"{field}['boxes']: expected a float32 tensor (N, 4), got {_describe(boxes)}")
        if not isinstance(labels, Tensor) or labels.dtype != torch.int64 or labels.dim() != 1:
            raise ValueError(f"{field}['labels']: expected an int64 tensor (N,), got {_describe(labels)}")
        if labels.shape[0] != boxes.shape[0]:
            raise ValueError(f"{field}: {boxes.shape[0]} boxes but {labels.shape[0]} labels")
        if values is None:  # the values where reading them costs no device sync (`check_targets`)
            values = boxes.device.type == "cpu" and labels.device.type == "cpu"
        if not values:
            return
        if labels.numel() and (labels.min() < 1 or labels.max() >= num_classes):
            raise ValueError(
                f"{field}['labels']: labels must be in 1..{num_classes - 1} (0 is background), "
                f"got {sorted(set(labels.tolist()))}"
            )
        if boxes.numel():
            h, w = self.transform.sizes[FRAMES[frame]]
            if not torch.isfinite(boxes).all():
                raise ValueError(f"{field}['boxes']: not finite")
            if ((boxes[:, 2] <= boxes[:, 0]) | (boxes[:, 3] <= boxes[:, 1])).any():
                raise ValueError(f"{field}['boxes']: boxes need x2 > x1 and y2 > y1 (x1, y1, x2, y2 order)")
            if (
                (boxes[:, 0] < 0).any()
                or (boxes[:, 1] < 0).any()
                or (boxes[:, 2] > w).any()
                or (boxes[:, 3] > h).any()
            ):
                raise ValueError(
                    f"{field}['boxes']: boxes must lie inside the {w}x{h} (W x H) image of frame {frame!r}"
                )

    def _branch_inputs(
        self, name: str, idx: list[int], feats: dict[str, tuple[Tensor, dict[int, int]]],
        inputs: Mapping[str, Tensor] | None = None,
    ) -> list[Tensor]:
        xs = []
        if self.branches[name].fusion == "input":
            rows = torch.as_tensor(idx, device=next(iter(inputs.values())).device)
            return [self.transform(s, inputs[s].index_select(0, rows)) for s in self.branches[name].sensors]
        for s in self.branches[name].sensors:
            f, rows = feats[s]
            r = [rows[i] for i in idx]
            if r != list(range(f.shape[0])):
                f = f.index_select(0, torch.as_tensor(r, device=f.device))
            xs.append(f)
        return xs

    def forward(
        self,
        inputs: Mapping[str, Tensor],
        targets: list[dict[str, dict[str, Tensor]]] | None = None,
        selection: Any = None,
        meta: Sequence[Any] | None = None,
    ):
        batch = self._check_inputs(inputs)
        if meta is not None and len(meta) != batch:
            raise ValueError(f"meta: {len(meta)} entries for a batch of {batch}")
        if not self.training and targets is not None:
            raise ValueError("targets: only used in training mode; in eval mode use per_sample_losses()")
        if selection is None and self.gate is not None and getattr(self.gate, "reads", "features") == "features":
            # Algorithm 1 lines 2-4: every stem runs, the gate reads them, the branches reuse them
            features = self.extract_features(inputs)
            selection = self.expand_selection(self.gate(features, meta), batch)
            groups, needs = self._plan(inputs, selection)  # every needed sensor is in features
            feats = {s: (f, {i: i for i in range(batch)}) for s, f in features.items()}
        elif selection is None and self.gate is not None:
            # a gate that reads external context (or losses) decides before any stem runs; then
            # only the stems the selected branches need run (EcoFusion 4.2.1, Knowledge gating)
            selection = self.expand_selection(self.gate(None, meta), batch)
            groups, needs = self._plan(inputs, selection)
            feats = None
        else:
            selection = self.expand_selection(selection, batch)
            groups, needs = self._plan(inputs, selection)
            feats = None
        if self.training:
            if targets is None:
                raise ValueError("targets: required in training mode")
            self._check_targets(targets, selection)
        if feats is None:
            feats = self._run_stems(inputs, needs, batch)

        if self.training:
            losses: dict[str, dict[str, Tensor]] = {}
            total = None
            for name, idx in groups.items():
                branch = self.branches[name]
                branch_targets = [targets[i][branch.frame] for i in idx]
                losses[name] = branch(self._branch_inputs(name, idx, feats, inputs), branch_targets)
                term = (len(idx) / batch) * sum(losses[name].values())
                total = term if total is None else total + term
            return {"total": total, "branches": losses}

        detections: list[dict[str, dict[str, Tensor]]] = [{} for _ in range(batch)]
        for name, idx in groups.items():
            results = self.branches[name](self._branch_inputs(name, idx, feats, inputs))
            for i, result in zip(idx, results):
                detections[i][name] = result
        if self.fusion_block is not None:
            return self.fusion_block(detections, self.branch_frames, meta)
        return detections

    @torch.no_grad()
    def per_sample_losses(
        self,
        inputs: Mapping[str, Tensor],
        targets: list[dict[str, dict[str, Tensor]]],
        selection: Any = None,
        *,
        seed: int = 0,
    ) -> list[dict[str, dict[str, Tensor]]]:
        """Faster R-CNN multi-task losses of every sample for every selected branch, in eval mode.

        Nothing is updated (no gradients; normalisation layers keep their running statistics).
        Stems and branch backbones run batched in eval behaviour; the RPN and RoI heads then run in
        training behaviour (training proposal counts, random anchor/RoI sampling) on each sample
        alone, with torch's global RNG forked and re-seeded with `seed` for every (sample, branch),
        so the result does not depend on batch composition or order, and equals the losses of a
        batch-1 training-mode forward of that branch after `torch.manual_seed(seed)` whenever
        normalisation behaves the same (norm "group", or batch norm in eval mode).

        Args:
            inputs, targets: as for `forward` in training mode.
            selection: as for `forward`, except that None always means every branch (the gate is
                not consulted: these losses are what a gate is trained to predict).
            seed: RNG seed for the sampling.

        Returns:
            A list of B dicts branch name -> {four losses as 0-dim tensors}, for the sample's
            selected branches in branch order.
        """
        if self.training:
            raise RuntimeError("per_sample_losses needs eval mode (call model.eval() first)")
        batch = self._check_inputs(inputs)
        selection = self.expand_selection(selection, batch)
        groups, needs = self._plan(inputs, selection)
        self._check_targets(targets, selection)
        feats = self._run_stems(inputs, needs, batch)
        out: list[dict[str, dict[str, Tensor]]] = [{} for _ in range(batch)]
        for name, idx in groups.items():
            branch = self.branches[name]
            per = branch.per_sample_losses(
                self._branch_inputs(name, idx, feats, inputs), [targets[i][branch.frame] for i in idx], seed=seed
            )
            for i, losses in zip(idx, per):
                out[i][name] = losses
        return out

    @torch.no_grad()
    def detect_and_losses(
        self,
        inputs: Mapping[str, Tensor],
        targets: list[dict[str, dict[str, Tensor]]],
        *,
        seed: int = 0,
        features: Mapping[str, Tensor] | None = None,
    ) -> tuple[list[dict[str, dict[str, Tensor]]], list[dict[str, dict[str, Tensor]]]]:
        """Every branch's eval-mode detections (as `forward(inputs, selection=every branch)`) and
        per-sample losses (as `per_sample_losses(inputs, targets, seed=seed)`) from one run of the
        stems and of each branch's backbone: the same numbers as the two calls apart (the same
        batched operations on the same inputs), for the price of one forward and the loss heads.

        `features`: `extract_features(inputs, sensors)` already computed (what a gate read), used
        instead of running the stems again; it must hold every sensor the branches need. The same
        numbers as without it when `sensors` are exactly those (`stem_sensors()`): each stem then
        sees the same batch."""
        if self.training:
            raise RuntimeError("detect_and_losses needs eval mode (call model.eval() first)")
        batch = self._check_inputs(inputs)
        selection = self.expand_selection(None, batch)
        groups, needs = self._plan(inputs, selection)
        self._check_targets(targets, selection)
        if features is None:
            feats = self._run_stems(inputs, needs, batch)
        else:
            missing = [s for s in needs if s not in features]
            if missing:
                raise ValueError(f"features: no stem features for sensor(s) {', '.join(missing)} the branches need")
            feats = {s: (features[s], {i: i for i in range(batch)}) for s in needs}
        detections: list[dict[str, dict[str, Tensor]]] = [{} for _ in range(batch)]
        losses: list[dict[str, dict[str, Tensor]]] = [{} for _ in range(batch)]
        for name, idx in groups.items():
            branch = self.branches[name]
            dets, per = branch.detect_and_losses(
                self._branch_inputs(name, idx, feats, inputs), [targets[i][branch.frame] for i in idx], seed=seed
            )
            for i, d, lo in zip(idx, dets, per):
                detections[i][name] = d
                losses[i][name] = lo
        return detections, losses


def _batch_of(selection: Any) -> int:
    """Batch size implied by a selection for the union queries (1 unless per-sample lists)."""
    if isinstance(selection, Sequence) and not isinstance(selection, str) and selection:
        if all(isinstance(s, Sequence) and not isinstance(s, str) for s in selection):
            return len(selection)
    return 1


def _describe(x: Any) -> str:
    if isinstance(x, Tensor):
        return f"{x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def build_hydrafusion(
    *,
    profile: str | ModelProfile = "cpu",
    branches: Sequence[BranchSpec | Mapping[str, Any]] | None = None,
    gate: nn.Module | None = None,
    fusion_block: nn.Module | None = None,
    **overrides: Any,
) -> HydraFusion:
    """Build a HydraFusion network from a model profile.

    Args:
        profile: "cpu" (default), "paper" or another `configs/model/<name>.yaml`, or a ModelProfile.
        branches: the branch set, a list of BranchSpec or {"name", "sensors", "frame"} dicts;
            None keeps the profile's (HydraFusion's seven).
        gate, fusion_block: extension points, see HydraFusion.
        **overrides: any ModelProfile field (nested fields merge: `camera={"size": (64, 96)}`).

    Only the stems the branches need are built (one per modality). The model's `profile`
    attribute holds the resolved ModelProfile.

    Raises:
        UserError (a ValueError) naming the field for unknown profiles, keys or invalid values.
    """
    if branches is not None:
        overrides["branches"] = list(branches)
    prof = load_profile(profile, **overrides)
    used = {SENSORS[s].stem for b in prof.branches if b.fusion == "features" for s in b.sensors}
    stems = {
        name: build_stem(name, prof)
        for name in dict.fromkeys(s.stem for s in SENSORS.values())
        if name in used
    }
    model = HydraFusion(
        stems,
        {b.name: build_branch(b, prof) for b in prof.branches},
        gate,
        fusion_block,
        transform=SensorTransform(
            normalization=prof.normalization,
            sizes={"camera": prof.camera.size, "bev": prof.bev.size},
            strides={"camera": prof.camera.output_stride, "bev": prof.bev.output_stride},
        ),
    )
    model.profile = prof
    return model
