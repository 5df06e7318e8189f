"""Energy of a configuration (EcoFusion Section 3.2, Eq. 6) and of the sensors (Section 5.5.2,
Eq. 10-11).

**Compute energy, Eq. 6: E(phi) = P(phi) t(phi).** t is measured on the machine at hand, per
component: each stem on one sensor, each branch on its stem features, the fusion block on n
branches' detections (`study.eco.latency_energy.measure_latency`). A configuration's latency is additive:
the stems of the sensors its branches need, each once (stems are shared), plus its branches, plus
the fusion block (`LatencyModel.latency`); the sum is checked against configurations timed end to
end. P comes from an energy counter where one exists:

- NVML (NVIDIA GPUs: total energy since driver load, mJ) through `pynvml` (PyPI nvidia-ml-py),
  read only when importable and a GPU is present;
- RAPL (Intel / AMD CPUs: `/sys/class/powercap/intel-rapl:*/energy_uj`, uJ, wrapping at
  `max_energy_range_uj`);

otherwise P is a stated model: a constant machine power (`PowerModel`), by default the paper's
measured Drive PX2 under load, 45.4 W. Every energy figure carries its `source` ("measured: RAPL",
"measured: NVML", "modelled: 45.4 W (Drive PX2 under load, EcoFusion 3.2) x measured latency").

**Sensor energy, Eq. 10-11.** E_s = (P_s^meas + P_s^motor) / f_s with P_s^meas = P_s - P_s^motor;
E_total = E(phi) + sum_s E_s. Clock gating stops a sensor's measurements (P^meas = 0) but keeps
its motor turning (a spun-down lidar or radar needs seconds to restart), so an unused rotating
sensor still costs P^motor / f. Sensor figures: `SENSOR_DEVICES` (the paper's, Section 5.5.2).
Plain Python and numpy: no torch here.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

PX2_POWER_W = 45.4
"""EcoFusion 3.2: "We measured the PX2's average power consumption under load as 45.4 Watts"."""
POWER_PRESETS = {"px2": PX2_POWER_W}


# ----- compute power: counters and the model ---------------------------------------------------


@dataclass(frozen=True)
class PowerModel:
    """A constant machine power P [W] (Eq. 6 with P(phi) = P for every configuration)."""

    watts: float = PX2_POWER_W
    label: str = "Drive PX2 under load, EcoFusion 3.2"

    @property
    def source(self) -> str:
        return f"modelled: {self.watts:g} W ({self.label}) x measured latency"


def power_model(spec: str | float | None) -> PowerModel:
    """"px2" (45.4 W) or a number of watts -> PowerModel. ValueError naming the problem otherwise."""
    if spec is None or spec == "px2":
        return PowerModel()
    try:
        w = float(spec)
    except (TypeError, ValueError):
        raise ValueError(f"power: expected 'px2' or a power in watts, got {spec!r}") from None
    if not (w > 0 and w < float("inf")):
        raise ValueError(f"power: must be a finite number of watts > 0, got {spec!r}")
    return PowerModel(w, "stated machine power")


class RaplCounter:
    """Energy from Linux powercap RAPL: the sum of the top-level domains' `energy_uj` (packages),
    wrap-around corrected with each domain's `max_energy_range_uj`.

    `read()` -> cumulative microjoules (per-domain raw values); `joules(before, after)` -> J between
    two reads (at most one wrap per domain between reads).
    """

    name = "RAPL"

    def __init__(self, root: str = "/sys/class/powercap") -> None:
        self.domains = sorted(p for p in glob.glob(os.path.join(root, "intel-rapl:*"))
                              if os.path.basename(p).count(":") == 1)
        if not self.domains:
            raise OSError(f"no RAPL domains under {root}")
        self.ranges = []
        for d in self.domains:
            with open(os.path.join(d, "energy_uj")):
                pass  # readable, or OSError (root-only on recent kernels)
            rng = os.path.join(d, "max_energy_range_uj")
            self.ranges.append(int(open(rng).read()) if os.path.exists(rng) else 2**32)

    def read(self) -> list[int]:
        return [int(open(os.path.join(d, "energy_uj")).read()) for d in self.domains]

    def joules(self, before: Sequence[int], after: Sequence[int]) -> float:
        total = 0
        for b, a, r in zip(before, after, self.ranges):
            total += a - b if a >= b else a + r - b
        return total / 1e6


class NvmlCounter:
    """Energy of the NVIDIA GPU torch calls `device` from NVML's total-energy counter (mJ since the
    driver loaded), through `fusion.nvml.GpuEnergyMeter`: the NVML device is found by the CUDA
    device's UUID (NVML numbers devices its own way). OSError where it cannot be read."""

    name = "NVML"

    def __init__(self, device: str = "cuda", meter=None) -> None:
        if meter is None:
            import torch

            from fusion.nvml import GpuEnergyMeter

            if not torch.cuda.is_available():
                raise OSError("no CUDA GPU")
            dev = torch.device(device)
            index = dev.index if dev.index is not None else torch.cuda.current_device()
            meter = GpuEnergyMeter.for_uuid(str(torch.cuda.get_device_properties(index).uuid))
        if not meter.available:
            raise OSError("NVML has no energy counter for this GPU")
        self.meter = meter

    def read(self) -> int:
        value = self.meter.energy_mj()
        if value is None:
            raise OSError("the NVML energy counter stopped answering")
        return value

    def joules(self, before: int, after: int) -> float:
        return (after - before) / 1e3


def open_counter(kind: str = "auto", device: str = "cpu", rapl_root: str = "/sys/class/powercap"):
    """An energy counter for `device` ("cpu" -> RAPL, "cuda" -> NVML), or None where none can be
    read. `kind`: "auto", "rapl", "nvml" or "none"; an explicitly requested counter that cannot be
    opened raises OSError naming why."""
    if kind == "none":
        return None
    want = kind if kind != "auto" else ("nvml" if device.startswith("cuda") else "rapl")
    try:
        return NvmlCounter(device if device.startswith("cuda") else "cuda") if want == "nvml" else RaplCounter(rapl_root)
    except Exception as exc:  # missing module, no GPU, no sysfs, permission denied
        if kind != "auto":
            raise OSError(f"cannot read the {want.upper()} energy counter: {exc}") from None
        return None


# ----- latency and energy of configurations ----------------------------------------------------


@dataclass
class LatencyModel:
    """Measured component latencies [s] and what they predict for a configuration.

    Attributes:
        stems: sensor -> seconds of its stem on one frame.
        branches: branch -> seconds of the branch on its stem features (one frame).
        fusion: number of fused branches n (1..) -> seconds of the fusion block.
        branch_sensors: branch -> the sensors whose shared stems it needs (empty for branches that
            bring their own stem, fusion "input").
        energy: optional component -> measured joules ("stem:<sensor>", "branch:<name>",
            "fusion:<n>") from an energy counter; None when energy is modelled.
    """

    stems: dict[str, float]
    branches: dict[str, float]
    fusion: dict[int, float]
    branch_sensors: dict[str, tuple[str, ...]]
    energy: dict[str, float] | None = None
    meta: dict = field(default_factory=dict)

    def _parts(self, config: Sequence[str]) -> list[str]:
        sensors = sorted({s for b in config for s in self.branch_sensors[b]})
        return [f"stem:{s}" for s in sensors] + [f"branch:{b}" for b in config] + [f"fusion:{len(config)}"]

    def part_seconds(self, part: str) -> float:
        kind, name = part.split(":", 1)
        if kind == "stem":
            return self.stems[name]
        if kind == "branch":
            return self.branches[name]
        n = int(name)
        return self.fusion[n] if n in self.fusion else self.fusion[max(self.fusion)]

    def latency(self, config: Sequence[str]) -> float:
        """t(phi) [s]: shared stems once + branches + fusion block (additive model)."""
        return float(sum(self.part_seconds(p) for p in self._parts(config)))

    def measured_energy(self, config: Sequence[str]) -> float | None:
        """E(phi) [J] from the counter's component energies (additive), or None without a counter."""
        if self.energy is None:
            return None
        return float(sum(self.energy[p] for p in self._parts(config)))

    def to_dict(self) -> dict:
        return {"stems": self.stems, "branches": self.branches, "fusion": {str(k): v for k, v in self.fusion.items()},
                "branch_sensors": {k: list(v) for k, v in self.branch_sensors.items()}, "energy": self.energy,
                "meta": self.meta}

    @staticmethod
    def from_dict(d: Mapping) -> LatencyModel:
        return LatencyModel(dict(d["stems"]), dict(d["branches"]), {int(k): v for k, v in d["fusion"].items()},
                            {k: tuple(v) for k, v in d["branch_sensors"].items()}, d.get("energy"),
                            dict(d.get("meta", {})))


def configuration_energy(model: LatencyModel, configs: Sequence[Sequence[str]],
                         power: PowerModel | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """(latency [s] (n,), energy [J] (n,), source) of each configuration: Eq. 6 with the counter's
    measured component energies when the model has them, else P x t with `power` (default PX2)."""
    t = np.array([model.latency(c) for c in configs])
    if model.energy is not None:
        e = np.array([model.measured_energy(c) for c in configs])
        return t, e, f"measured: {model.meta.get('counter', 'energy counter')} (component energies summed)"
    power = power or PowerModel()
    return t, power.watts * t, power.source


# ----- sensors: clock gating (Section 5.5.2) ---------------------------------------------------


@dataclass(frozen=True)
class SensorDevice:
    """One physical sensor's power (EcoFusion Section 5.5.2).

    Fields:
        name: the device.
        power_w: [W] total power while measuring, P_s.
        motor_w: [W] of it spinning the motor, P_s^motor (0 for a camera).
        rate_hz: [Hz] measurement frequency f_s.
        source: where the figures come from.
    """

    name: str
    power_w: float
    motor_w: float
    rate_hz: float
    source: str

    @property
    def measure_w(self) -> float:
        """P_s^meas = P_s - P_s^motor (Eq. 10)."""
        return self.power_w - self.motor_w


SENSOR_DEVICES: dict[str, SensorDevice] = {
    "radar": SensorDevice("Navtech CTS350-X radar", 24.0, 2.4, 4.0,
                          "24 W [EcoFusion ref. 18], 2.4 W of it the motor so p_meas = 21.6 W (Section 5.5.2); "
                          "4 Hz scans (RADIATE)"),
    "lidar": SensorDevice("Velodyne HDL-32E lidar", 12.0, 2.4, 10.0,
                          "12 W [ref. 13]; p_meas = 9.6 W estimated by the paper from comparable motors "
                          "(Section 5.5.2), so 2.4 W motor; 10 Hz"),
    "zed": SensorDevice("ZED stereo camera", 1.9, 0.0, 15.0,
                        "1.9 W [ref. 24], no motor; 15 Hz; one device for both eyes"),
}
"""Physical sensor -> power figures (EcoFusion Section 5.5.2)."""

SENSOR_DEVICE_OF = {"camera_left": "zed", "camera_right": "zed", "fwd_lidar": "lidar", "lidar": "lidar",
                    "radar": "radar"}
"""Network input -> the physical sensor that measures it (the forward lidar is the lidar's points
projected into the camera; both camera inputs come from the one ZED)."""

GATING_MODES = ("clock", "eq11", "off")
SENSOR_PERIODS = ("frame", "measurement")
"""What one sensor's energy is charged over (`total_energy`): "frame", one period of the fused output
at FRAME_HZ for every sensor (EcoFusion Table 3's arithmetic: late fusion 3.798 + (24 + 12 + 1.9) / 4 =
13.27 J, city 1.379 + (2.4 + 12 + 1.9) / 4 = 5.45 J; and the energy the rig draws per fused frame);
"measurement", one measurement of that sensor at its own rate f_s (Eq. 10 read literally: a 10 Hz
lidar's 0.1 s beside a 4 Hz radar's 0.25 s, a sum over different durations)."""
FRAME_HZ = 4.0
"""[Hz] the fused output's rate: the radar's scan rate, the slowest sensor (RADIATE; EcoFusion Table 3
divides every sensor's power by 4)."""


def sensor_energy(device: SensorDevice, measuring: bool = True, rate_hz: float | None = None) -> float:
    """Eq. 10: E_s = (P^meas + P^motor) / f [J]; clock-gated: P^meas = 0. f is the device's own rate
    f_s, or `rate_hz` (the fused frame rate, for the "frame" period)."""
    rate = device.rate_hz if rate_hz is None else rate_hz
    if not rate > 0:
        raise ValueError(f"rate_hz: must be > 0, got {rate}")
    return ((device.measure_w if measuring else 0.0) + device.motor_w) / rate


def devices_of(sensors: Sequence[str]) -> set[str]:
    return {SENSOR_DEVICE_OF[s] for s in sensors}


def total_energy(compute_j: float, sensors: Sequence[str], mode: str = "clock",
                 devices: Mapping[str, SensorDevice] = SENSOR_DEVICES, period: str = "frame") -> float:
    """Eq. 11: E_total = E(phi) + sum_s E_s for a configuration consuming `sensors` (network inputs).

    mode "clock": every device counts; those phi does not use are clock-gated (motor only, the
    text of 5.5.2); "eq11": only the devices phi uses (Eq. 11 as printed: unused ones cost
    nothing); "off": every device measures (no gating, the late-fusion baseline's rig).
    period: each sensor's energy over one fused frame at FRAME_HZ ("frame", the paper's Table 3,
    the default) or over one of its own measurements ("measurement"); see SENSOR_PERIODS.
    """
    if mode not in GATING_MODES:
        raise ValueError(f"mode: expected one of {GATING_MODES}, got {mode!r}")
    if period not in SENSOR_PERIODS:
        raise ValueError(f"period: expected one of {SENSOR_PERIODS}, got {period!r}")
    rate = FRAME_HZ if period == "frame" else None
    used = devices_of(sensors)
    total = float(compute_j)
    for name, dev in devices.items():
        if mode == "off":
            total += sensor_energy(dev, True, rate)
        elif name in used:
            total += sensor_energy(dev, True, rate)
        elif mode == "clock":
            total += sensor_energy(dev, False, rate)
    return total
