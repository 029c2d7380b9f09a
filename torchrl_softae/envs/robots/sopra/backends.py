"""The SoPrA hardware interface: motion capture + valve array, behind two small protocols.

A backend is a :class:`MotionCapture` (6-DoF poses of named rigid bodies with timestamps; a lost
body arrives as NaN) and a :class:`ValveArray` (send six absolute chamber pressures in mbar, read
the measured ones, vent). Real implementations: :class:`QualisysMotionCapture` (QTM real-time
protocol through ``qtm-rt``) and :class:`ModbusValveArray` (Modbus TCP through ``pymodbus``, the
register map in a config file). The simulated twin (``sim.py``) implements both. Hardware packages
are optional (``pip install torchrl-softae[sopra]``) and imported only when those classes are used.
"""
from __future__ import annotations

import asyncio
import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from torchrl_softae.envs.robots.rotations import rotation_to_quaternion

__all__ = [
    "Pose",
    "MotionCapture",
    "ValveArray",
    "RecordingValveArray",
    "QualisysMotionCapture",
    "ModbusValveArray",
    "ModbusMap",
    "rotation_to_quaternion",
]

N_CHAMBERS = 6


@dataclass
class Pose:
    """A rigid body's pose: position [m] (3,), unit quaternion (w, x, y, z) (4,), capture time [s]."""

    position: np.ndarray
    quaternion: np.ndarray
    timestamp: float

    @property
    def valid(self) -> bool:
        return bool(np.all(np.isfinite(self.position)) and np.all(np.isfinite(self.quaternion)))


@runtime_checkable
class MotionCapture(Protocol):
    def start(self) -> None: ...

    def latest(self) -> tuple[int, dict[str, Pose]]:
        """(frame number, poses by body name) of the newest frame; frame -1 before the first."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class ValveArray(Protocol):
    def send_pressures(self, mbar: np.ndarray) -> None: ...

    def read_pressures(self) -> np.ndarray: ...

    def vent(self) -> None: ...

    def close(self) -> None: ...


class RecordingValveArray:
    """A valve array that talks to nothing and records every command: the dry-run valves."""

    def __init__(self):
        self.commands: list[np.ndarray] = []
        self.vents = 0
        self._last = np.zeros(N_CHAMBERS)

    def send_pressures(self, mbar):
        self._last = np.asarray(mbar, dtype=np.float64).copy()
        self.commands.append(self._last.copy())

    def read_pressures(self):
        return self._last.copy()

    def vent(self):
        self.vents += 1
        self._last = np.zeros(N_CHAMBERS)
        self.commands.append(self._last.copy())

    def close(self):
        pass


# ---------------------------------------------------------------------------- Qualisys
class QualisysMotionCapture:
    """Streams 6-DoF bodies from Qualisys Track Manager over its real-time protocol (``qtm-rt``).

    An asyncio client runs in a background thread; :meth:`latest` returns the newest frame. QTM
    reports positions in mm and a rotation matrix (column-major); lost bodies come as NaN.

    Args:
        host, port: QTM's RT server (little-endian port 22223 by default).
        bodies: names of the rigid bodies to return (as defined in QTM), e.g. base, mid, tip.
        frequency: requested stream rate [Hz] (``None`` = all frames).
        version: RT protocol version.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 22223, bodies=("base", "mid", "tip"),
                 frequency: float | None = 100.0, version: str = "1.25", timeout: float = 5.0):
        self.host, self.port, self.bodies = host, port, tuple(bodies)
        self.frequency, self.version, self.timeout = frequency, version, timeout
        self._frame: tuple[int, dict[str, Pose]] = (-1, {})
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._conn = None
        self._t0 = time.monotonic()

    def start(self) -> None:
        try:
            import qtm_rt  # noqa: F401
        except ImportError as e:
            raise ImportError("QualisysMotionCapture needs qtm-rt: pip install 'torchrl-softae[sopra]'") from e
        self._thread = threading.Thread(target=self._run, name="qualisys-rt", daemon=True)
        self._thread.start()
        if not self._ready.wait(self.timeout + 1):
            raise TimeoutError(f"no answer from QTM at {self.host}:{self.port} within {self.timeout} s")
        if self._error is not None:
            raise ConnectionError(f"QTM at {self.host}:{self.port}: {self._error}")

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._connect())
        except BaseException as e:  # noqa: BLE001  (reported to start())
            self._error = e
            self._ready.set()
            return
        self._ready.set()
        self._loop.run_forever()

    async def _connect(self) -> None:
        import xml.etree.ElementTree as ET

        import qtm_rt

        conn = await qtm_rt.connect(self.host, port=self.port, version=self.version, timeout=self.timeout)
        if conn is None:
            raise ConnectionError("connection refused or protocol version rejected")
        self._conn = conn
        xml = await conn.get_parameters(parameters=["6d"])
        names = [el.text for el in ET.fromstring(xml).iter("Name")]
        missing = [b for b in self.bodies if b not in names]
        if missing:
            raise KeyError(f"QTM has no 6DoF bodies {missing}; it streams {names}")
        self._index = {b: names.index(b) for b in self.bodies}
        frames = f"frequency:{int(self.frequency)}" if self.frequency else "allframes"
        await conn.stream_frames(frames=frames, components=["6d"], on_packet=self._on_packet)

    def _on_packet(self, packet) -> None:
        _, bodies = packet.get_6d()
        stamp = packet.timestamp * 1e-6  # QTM timestamps are in microseconds
        poses = {}
        for name, i in self._index.items():
            pos, rot = bodies[i]
            R = np.asarray(rot.matrix, dtype=np.float64).reshape(3, 3, order="F")
            poses[name] = Pose(np.asarray([pos.x, pos.y, pos.z], dtype=np.float64) / 1000.0,
                               rotation_to_quaternion(R), stamp)
        with self._lock:
            self._frame = (packet.framenumber, poses)

    def latest(self) -> tuple[int, dict[str, Pose]]:
        with self._lock:
            return self._frame

    def close(self) -> None:
        if self._loop is not None and self._loop.is_running():
            async def stop():
                if self._conn is not None:
                    try:
                        await self._conn.stream_frames_stop()
                    except Exception:  # noqa: BLE001
                        pass
                    self._conn.disconnect()

            fut = asyncio.run_coroutine_threadsafe(stop(), self._loop)
            try:
                fut.result(timeout=2)
            except Exception:  # noqa: BLE001
                pass
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=2)


# ---------------------------------------------------------------------------- Modbus
@dataclass
class ModbusMap:
    """Register map of a Modbus TCP valve array (no public map exists for the lab's Festo array:
    fill it from your device's manual). Pressures travel as unsigned 16-bit counts:
    ``count = mbar / mbar_per_count``.
    """

    host: str = "127.0.0.1"
    port: int = 502
    device_id: int = 1
    setpoint_register: int = 0  # first of six consecutive holding registers (commanded pressure)
    measured_register: int = 16  # first of six consecutive registers holding the measured pressure
    measured_is_input_register: bool = False
    mbar_per_count: float = 1.0
    timeout: float = 1.0
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_file(cls, path: str | Path) -> "ModbusMap":
        """JSON or YAML file with the fields above."""
        text = Path(path).read_text()
        if str(path).endswith((".yaml", ".yml")):
            import yaml

            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
        unknown = set(data) - {f for f in cls.__dataclass_fields__}
        if unknown:
            raise ValueError(f"{path}: unknown Modbus map keys {sorted(unknown)}")
        return cls(**data)


class ModbusValveArray:
    """Six proportional pressure valves over Modbus TCP (``pymodbus``).

    Every read and write is bounded by the map's ``timeout`` (one retry): a device that stops
    answering raises (``ModbusIOException``) instead of hanging the control loop."""

    def __init__(self, config: ModbusMap | str | Path):
        try:
            from pymodbus.client import ModbusTcpClient
        except ImportError as e:
            raise ImportError("ModbusValveArray needs pymodbus: pip install 'torchrl-softae[sopra]'") from e
        self.map = config if isinstance(config, ModbusMap) else ModbusMap.from_file(config)
        if not (self.map.timeout > 0 and np.isfinite(self.map.timeout)):
            raise ValueError(f"ModbusValveArray: timeout={self.map.timeout!r} s, expected a finite value > 0")
        del ModbusTcpClient  # imported above only to fail early with the install hint
        self.client = self._connect()

    def _check(self, result, what: str):
        if result.isError():
            raise IOError(f"Modbus {what} failed: {result}")
        return result

    def send_pressures(self, mbar) -> None:
        mbar = np.asarray(mbar, dtype=np.float64)
        if mbar.shape != (N_CHAMBERS,) or not np.all(np.isfinite(mbar)) or np.any(mbar < 0):
            raise ValueError(f"ModbusValveArray: pressures {mbar} must be 6 finite values >= 0 mbar")
        counts = np.round(mbar / self.map.mbar_per_count).astype(int)
        if np.any(counts > 0xFFFF):
            raise ValueError(f"ModbusValveArray: {mbar} mbar exceeds the 16-bit register range")
        self._check(self.client.write_registers(self.map.setpoint_register, counts.tolist(),
                                                device_id=self.map.device_id), "write setpoints")

    def read_pressures(self) -> np.ndarray:
        read = self.client.read_input_registers if self.map.measured_is_input_register else self.client.read_holding_registers
        r = self._check(read(self.map.measured_register, count=N_CHAMBERS, device_id=self.map.device_id), "read pressures")
        return np.asarray(r.registers, dtype=np.float64) * self.map.mbar_per_count

    def _connect(self):
        from pymodbus.client import ModbusTcpClient

        client = ModbusTcpClient(self.map.host, port=self.map.port, timeout=self.map.timeout, retries=1)
        if not client.connect():
            raise ConnectionError(f"no Modbus TCP server at {self.map.host}:{self.map.port}")
        return client

    def vent(self) -> None:
        """Zero every setpoint; if the connection does not answer (within the timeout), try once more
        on a fresh connection. Raises when both fail (the safety layer logs it loudly)."""
        try:
            self.send_pressures(np.zeros(N_CHAMBERS))
        except Exception:  # noqa: BLE001
            self.client.close()
            self.client = self._connect()
            self.send_pressures(np.zeros(N_CHAMBERS))

    def close(self) -> None:
        self.client.close()
