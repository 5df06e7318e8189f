"""Measured GPU energy from NVIDIA's management library (NVML), read with ctypes.

`nvmlDeviceGetTotalEnergyConsumption` is the GPU's energy counter in millijoules since the driver
was loaded (Volta and later). The energy of a piece of work is the counter's difference across it,
the whole board's consumption while the work ran (idle power included), which is what EcoFusion
means by measured energy (EcoFusion 4.3 measures the platform under load). Where there is no NVML
(no NVIDIA driver, an older GPU) `GpuEnergyMeter.available` is False and every reading is None:
callers then label energy as modelled, never as measured.
"""

from __future__ import annotations

import ctypes

_NVML = None


def _lib():
    global _NVML
    if _NVML is None:
        try:
            lib = ctypes.CDLL("libnvidia-ml.so.1")
            if lib.nvmlInit_v2() != 0:
                raise OSError("nvmlInit failed")
            _NVML = lib
        except (OSError, AttributeError):
            _NVML = False
    return _NVML or None


class GpuEnergyMeter:
    """Energy counter and power of one GPU (`index`: NVML's device index, as CUDA's by default)."""

    def __init__(self, index: int = 0) -> None:
        self.handle = None
        lib = _lib()
        if lib is not None:
            handle = ctypes.c_void_p()
            if lib.nvmlDeviceGetHandleByIndex_v2(ctypes.c_uint(index), ctypes.byref(handle)) == 0:
                self.handle = handle
        if self.handle is not None and self.energy_mj() is None:
            self.handle = None

    @property
    def available(self) -> bool:
        return self.handle is not None

    def energy_mj(self) -> int | None:
        """The board's energy counter [mJ] since the driver was loaded, or None."""
        if self.handle is None:
            return None
        lib = _lib()
        value = ctypes.c_ulonglong()
        if lib is None or lib.nvmlDeviceGetTotalEnergyConsumption(self.handle, ctypes.byref(value)) != 0:
            return None
        return int(value.value)

    def power_w(self) -> float | None:
        """The board's power draw now [W], or None."""
        lib = _lib()
        value = ctypes.c_uint()
        if self.handle is None or lib.nvmlDeviceGetPowerUsage(self.handle, ctypes.byref(value)) != 0:
            return None
        return value.value / 1000.0
