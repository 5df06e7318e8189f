"""Measured GPU energy from NVIDIA's management library (NVML), read with ctypes.

`nvmlDeviceGetTotalEnergyConsumption` is the GPU's energy counter in millijoules since the driver
was loaded (Volta and later). The energy of a piece of work is the counter's difference across it,
the whole board's consumption while the work ran (idle power included), which is what EcoFusion
means by measured energy (EcoFusion 4.3 measures the platform under load). Where there is no NVML
(no NVIDIA driver, an older GPU) `GpuEnergyMeter.available` is False and every reading is None:
callers then label energy as modelled, never as measured.

The counter moves in steps of 20-100 ms (the driver's update period), so a difference across a
few forwards of tens of milliseconds can be zero or twice the truth: measure over seconds
(`study.bench.nets.measure_energy`). NVML numbers its devices its own way; `GpuEnergyMeter.for_uuid`
finds the one torch calls cuda:N by UUID.
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


def same_gpu(cuda_uuid: str, nvml_uuid: str) -> bool:
    """Whether torch's `get_device_properties(i).uuid` (hex digits in 8-4-4-4-12 groups) and NVML's
    `nvmlDeviceGetUUID` ("GPU-" and the same groups; "MIG-..." for a MIG slice) name one device."""
    def bare(u: str) -> str:
        u = str(u).strip().lower()
        for prefix in ("gpu-", "mig-"):
            if u.startswith(prefix):
                u = u[len(prefix):]
        return u.replace("-", "")

    return bool(bare(cuda_uuid)) and bare(cuda_uuid) == bare(nvml_uuid)


class GpuEnergyMeter:
    """Energy counter and power of one GPU. `index`: NVML's device index, which is not CUDA's in
    general (CUDA_VISIBLE_DEVICES renumbers, CUDA orders fastest first): `for_uuid` finds the NVML
    device of a CUDA device by its UUID. `lib`: the NVML library (default: libnvidia-ml, loaded once)."""

    def __init__(self, index: int | None = 0, lib=None) -> None:
        self.handle = None
        self._nvml = lib if lib is not None else _lib()
        if self._nvml and index is not None:
            handle = ctypes.c_void_p()
            if self._nvml.nvmlDeviceGetHandleByIndex_v2(ctypes.c_uint(index), ctypes.byref(handle)) == 0:
                self.handle = handle
        if self.handle is not None and self.energy_mj() is None:
            self.handle = None

    @classmethod
    def for_uuid(cls, uuid: str, lib=None) -> GpuEnergyMeter:
        """The meter of the NVML device whose UUID is `uuid` (torch's device UUID); unavailable
        (every reading None) when NVML has no such device."""
        lib = lib if lib is not None else _lib()
        index = None
        if lib is not None:
            for i, nvml_uuid in enumerate(nvml_uuids(lib)):
                if nvml_uuid is not None and same_gpu(uuid, nvml_uuid):
                    index = i
                    break
        return cls(index, lib=lib if lib is not None else False)

    @property
    def available(self) -> bool:
        return self.handle is not None

    def energy_mj(self) -> int | None:
        """The board's energy counter [mJ] since the driver was loaded, or None."""
        if self.handle is None or not self._nvml:
            return None
        value = ctypes.c_ulonglong()
        if self._nvml.nvmlDeviceGetTotalEnergyConsumption(self.handle, ctypes.byref(value)) != 0:
            return None
        return int(value.value)

    def power_w(self) -> float | None:
        """The board's power draw now [W], or None."""
        value = ctypes.c_uint()
        if self.handle is None or not self._nvml or self._nvml.nvmlDeviceGetPowerUsage(self.handle, ctypes.byref(value)) != 0:
            return None
        return value.value / 1000.0


def nvml_uuids(lib) -> list[str | None]:
    """The UUID of every NVML device, in NVML's index order (None where it cannot be read)."""
    count = ctypes.c_uint()
    if lib.nvmlDeviceGetCount_v2(ctypes.byref(count)) != 0:
        return []
    out: list[str | None] = []
    for i in range(count.value):
        handle = ctypes.c_void_p()
        buf = ctypes.create_string_buffer(96)  # NVML_DEVICE_UUID_V2_BUFFER_SIZE
        if (lib.nvmlDeviceGetHandleByIndex_v2(ctypes.c_uint(i), ctypes.byref(handle)) != 0
                or lib.nvmlDeviceGetUUID(handle, buf, ctypes.c_uint(len(buf))) != 0):
            out.append(None)
        else:
            out.append(buf.value.decode(errors="replace"))
    return out
