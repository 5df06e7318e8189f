"""Physical degradation of the raw observations by one WeatherState, plus obstruction and failure.

Importing this package registers every model (camera, lidar, radar) in `DEGRADATIONS`;
`Degrader` applies them to a frame's Observations and returns the parameters it drew.
"""

from __future__ import annotations

import dataclasses
import time
from collections import defaultdict

from sensors.degrade import camera as _camera  # noqa: F401  (registers)
from sensors.degrade import lidar as _lidar  # noqa: F401
from sensors.degrade import radar as _radar  # noqa: F401
from sensors.degrade.base import DEGRADATIONS, OBSTRUCTION_PROBABILITY, Degradation, DegradeContext
from sensors.degrade.lidar import LIDAR_FOG_MODELS
from sim.scenario import Context, stream

CAMERAS = ("camera_left", "camera_right")


class _Stream:
    """A model's random stream, stream(*keys), derived on the first draw: deriving one costs ~50 us
    and most models are inactive in most frames (their sample_params returns None without drawing)."""

    __slots__ = ("_keys", "_rng")

    def __init__(self, *keys) -> None:
        self._keys = keys
        self._rng = None

    def __getattr__(self, name: str):
        if self._rng is None:
            self._rng = stream(*self._keys)
        return getattr(self._rng, name)


class Degrader:
    """Applies the registered models to one sequence's frames.

    Each model draws from its own stream of (sequence seed, frame, model, camera), so whether one
    model is active never changes what another draws; faults that persist over a sequence come
    from a sequence-level stream (DegradeContext.sequence).

    Args:
        calib: the sequence's Calibration. context: context name. seed: the sequence seed.
        obstructions: include the obstruction/failure models (False: weather only).
        lidar_fog: lidar fog model, a name in LIDAR_FOG_MODELS ("ours" or "hahner").
    """

    def __init__(self, calib, context: str, seed: int, obstructions: bool = True, lidar_fog: str = "ours") -> None:
        self.seed = int(seed)
        self.obstructions = obstructions
        LIDAR_FOG_MODELS.get(lidar_fog)  # UserError naming the choices
        self.lidar_fog = lidar_fog
        self.sequence: dict = {"_rng": stream(self.seed, "degrade-sequence")}
        self.calib = calib
        self.context = Context.parse(context)
        self.timings: dict[str, float] = defaultdict(float)

    def _models(self) -> list[tuple[str, Degradation]]:
        return [(n, m) for n, m in DEGRADATIONS.items() if self.obstructions or m.kind != "obstruction"]

    def apply(self, obs, frame_index: int):
        """Degrade Observations `obs` (not modified) -> (new Observations, params by model)."""
        out = dataclasses.replace(obs)
        weather = obs.weather
        params: dict = {}
        for name, model in self._models():
            targets = CAMERAS if model.sensor == "camera" else (model.sensor,)
            for target in targets:
                ctx = DegradeContext(self.calib, self.context, self.sequence,
                                     camera=target if model.sensor == "camera" else "", frame_index=frame_index,
                                     lidar_fog=self.lidar_fog)
                rng = _Stream(self.seed, "degrade", frame_index, name, target)
                p = model.sample_params(rng, weather, ctx)
                if p is None:
                    continue
                t = time.perf_counter()
                setattr(out, target, model.apply(getattr(out, target), p, ctx))
                self.timings[name] += time.perf_counter() - t
                if model.sensor == "camera":
                    params.setdefault(name, {})[target] = p
                else:
                    params[name] = p
        return out, params


__all__ = ["DEGRADATIONS", "LIDAR_FOG_MODELS", "OBSTRUCTION_PROBABILITY", "Degrader", "DegradeContext", "Degradation"]
