"""SoPrA: safety layer (fuzzed), real protocols on loopback (Modbus TCP, QTM RT), the twin env."""
import asyncio
import socket
import struct
import threading
import time

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from torchrl_softae.envs.robots.sopra import (
    SOPRA_TARGETS,
    ModbusMap,
    ModbusValveArray,
    Pose,
    QualisysMotionCapture,
    RecordingValveArray,
    SafetyFault,
    SafetyLayer,
    SafetyLimits,
    SoPrAEnv,
    sopra_layout,
)
from torchrl_softae.envs.robots.sopra.env import SOPRA_TARGET_PRESSURES


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------ safety
class FlakyValves(RecordingValveArray):
    def __init__(self):
        super().__init__()
        self.fail_next = False
        self.sent = []  # (kind, pressures)

    def send_pressures(self, mbar):
        if self.fail_next:
            self.fail_next = False
            raise IOError("valve bus timeout")
        self.sent.append(("cmd", np.asarray(mbar, float).copy()))
        super().send_pressures(mbar)

    def vent(self):
        self.sent.append(("vent", np.zeros(6)))
        super().vent()


def _pose(p):
    return Pose(np.asarray(p, float), np.array([1.0, 0, 0, 0]), 0.0)


event = st.one_of(
    st.tuples(st.just("cmd"), st.lists(st.one_of(st.floats(-5000, 5000), st.just(float("nan")), st.just(float("inf"))),
                                       min_size=6, max_size=6)),
    st.tuples(st.just("fresh"), st.floats(-0.4, 0.4)),
    st.tuples(st.just("stale"), st.floats(0.0, 1.0)),
    st.tuples(st.just("nan"), st.just(0.0)),
    st.tuples(st.just("raise"), st.just(0.0)),
    st.tuples(st.just("rearm"), st.just(0.0)),
)


@settings(max_examples=150, deadline=None, derandomize=True)
@given(st.lists(event, min_size=1, max_size=40))
def test_safety_layer_invariants_under_fuzz(events):
    lim = SafetyLimits(p_max=400.0, max_rate=50.0)
    valves = FlakyValves()
    safety = SafetyLayer(valves, lim, control_period=0.1, install_handlers=False, watchdog=False)
    now, frame = 0.0, 0
    for kind, val in events:
        vents_before, sent_before, latched_before = safety.vent_count, len(valves.sent), safety.latched
        try:
            if kind == "cmd":
                safety.command(np.array(val))
            elif kind == "raise":
                valves.fail_next = True
                safety.command(safety.last_command + 10)
            elif kind == "rearm":
                safety.rearm()
                valves.sent.append(("rearm", np.zeros(6)))
            else:
                if kind == "fresh":
                    frame += 1
                    now += 0.1
                    tip = np.array([0.0, val, -0.25])
                    poses = {"base": _pose([0, 0, 0]), "tip": _pose(tip)}
                elif kind == "stale":
                    now += val
                    tip, poses = None, {"base": _pose([0, 0, 0])}
                else:
                    frame += 1
                    now += 0.1
                    tip, poses = None, {"base": _pose([0, 0, 0]), "tip": _pose([np.nan] * 3)}
                safety.check_frame(frame, poses, now, tip)
        except SafetyFault:
            if latched_before is not None and kind in ("cmd", "raise"):
                assert len(valves.sent) == sent_before  # refused: nothing reached the valves
            else:
                assert safety.vent_count == vents_before + 1  # every new fault ends in a vent
                assert valves.sent[-1][0] == "vent" and (safety.last_command == 0).all()
            assert safety.latched is not None
    prev, latched = np.zeros(6), False
    for kind, p in valves.sent:
        assert (p >= 0).all() and (p <= lim.p_max).all()  # never outside [0, p_max]
        if kind == "cmd":
            assert not latched  # no command between a fault's vent and a re-arm
            assert np.abs(p - prev).max() <= lim.max_rate + 1e-9  # never faster than the rate limit
        latched = (latched or kind == "vent") and kind != "rearm"
        prev = p
    safety.close()
    assert valves.sent[-1][0] == "vent"


def test_safety_limits_validation_and_dry_run():
    with pytest.raises(ValueError, match="p_max=-1"):
        SafetyLimits(p_max=-1)
    with pytest.raises(ValueError, match="workspace_low"):
        SafetyLimits(workspace_low=(0, 0, 0), workspace_high=(0, 0, 0))

    class Untouchable:
        def __getattr__(self, name):
            raise AssertionError(f"dry run touched the valves ({name})")

    safety = SafetyLayer(Untouchable(), dry_run=True, install_handlers=False)
    safety.command(np.full(6, 100.0))
    safety.close()
    assert isinstance(safety.valves, RecordingValveArray) and safety.valves.vents == 1


def test_sigint_vents():
    import os
    import signal

    valves = RecordingValveArray()
    safety = SafetyLayer(valves, install_handlers=True)
    safety.command(np.full(6, 50.0))
    with pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)
    assert valves.vents >= 1 and (valves.read_pressures() == 0).all()
    safety.close()


# ------------------------------------------------------------------------------------ Modbus
def test_modbus_backend_against_a_pymodbus_server_on_loopback(tmp_path):
    from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
    from pymodbus.server import ServerAsyncStop, StartAsyncTcpServer

    port = _free_port()
    block = ModbusSequentialDataBlock(1, [0] * 64)  # data block addresses are 1-based
    context = ModbusServerContext(devices=ModbusDeviceContext(hr=block), single=True)
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=lambda: loop.run_until_complete(
        StartAsyncTcpServer(context=context, address=("127.0.0.1", port))), daemon=True)
    thread.start()
    cfg = tmp_path / "valves.json"
    cfg.write_text(f'{{"host": "127.0.0.1", "port": {port}, "setpoint_register": 0, "measured_register": 16, "mbar_per_count": 0.5}}')
    valves = None
    for _ in range(50):  # the server needs a moment to bind
        try:
            valves = ModbusValveArray(str(cfg))
            break
        except ConnectionError:
            time.sleep(0.05)
    assert valves is not None
    from pymodbus.client import ModbusTcpClient

    device = ModbusTcpClient("127.0.0.1", port=port)  # a second client inspects the device's registers
    assert device.connect()
    try:
        valves.send_pressures(np.array([0, 100, 200, 300, 400, 1200.0]))
        regs = device.read_holding_registers(0, count=6).registers  # what the device received, in counts
        assert list(regs) == [0, 200, 400, 600, 800, 2400]
        device.write_registers(16, [10, 20, 30, 40, 50, 60])  # the device's measured pressures
        np.testing.assert_allclose(valves.read_pressures(), [5, 10, 15, 20, 25, 30])
        valves.vent()
        assert list(device.read_holding_registers(0, count=6).registers) == [0] * 6
        with pytest.raises(ValueError, match="finite values >= 0"):
            valves.send_pressures(np.array([0, 0, 0, 0, 0, -1.0]))
    finally:
        valves.close()
        device.close()
        asyncio.run_coroutine_threadsafe(ServerAsyncStop(), loop).result(timeout=5)
    with pytest.raises(ValueError, match="unknown Modbus map keys"):
        bad = tmp_path / "bad.json"
        bad.write_text('{"hots": "x"}')
        ModbusMap.from_file(bad)


# ------------------------------------------------------------------------------------ QTM RT
class QTMStandIn:
    """Speaks the part of Qualisys' RT protocol (little endian, v1.x) that the client uses:
    version, getparameters 6d, streamframes ... 6d, streamframes stop."""

    def __init__(self, bodies, frames):
        self.bodies, self.frames = bodies, frames  # frames: list of {name: (pos_mm, R) or None}
        self.port = _free_port()
        self.commands = []

    @staticmethod
    def packet(ptype, payload):
        return struct.pack("<II", 8 + len(payload), ptype) + payload

    def frame_packet(self, number, bodies):
        comp = struct.pack("<ihh", len(bodies), 0, 0)
        for b in bodies:
            if b is None:
                comp += struct.pack("<3f", *[float("nan")] * 3) + struct.pack("<9f", *[float("nan")] * 9)
            else:
                pos, R = b
                comp += struct.pack("<3f", *pos) + struct.pack("<9f", *np.asarray(R).reshape(-1, order="F"))
        comp = struct.pack("<II", 8 + len(comp), 5) + comp
        return self.packet(3, struct.pack("<qII", number * 10_000, number, 1) + comp)

    async def handle(self, reader, writer):
        buf = b""
        streaming = None
        while True:
            data = await reader.read(4096)
            if not data:
                break
            buf += data
            while len(buf) >= 8:
                size, ptype = struct.unpack_from("<II", buf)
                if len(buf) < size:
                    break
                cmd = buf[8:size].rstrip(b"\0").decode().lower()
                buf = buf[size:]
                self.commands.append(cmd)
                if cmd.startswith("version"):
                    writer.write(self.packet(1, b"Version set to 1.25\0"))
                elif cmd == "getparameters 6d":
                    xml = "<QTM_Parameters_Ver_1.25><The_6D>" + "".join(
                        f"<Body><Name>{b}</Name></Body>" for b in self.bodies) + "</The_6D></QTM_Parameters_Ver_1.25>"
                    writer.write(self.packet(2, xml.encode() + b"\0"))
                elif cmd.startswith("streamframes stop"):
                    if streaming:
                        streaming.cancel()
                elif cmd.startswith("streamframes"):
                    async def stream():
                        for i, f in enumerate(self.frames):
                            writer.write(self.frame_packet(i, [f.get(b) for b in self.bodies]))
                            await writer.drain()
                            await asyncio.sleep(0.01)
                    streaming = asyncio.ensure_future(stream())
            await writer.drain()

    def serve(self):
        loop = asyncio.new_event_loop()
        self.loop = loop

        async def main():
            self.server = await asyncio.start_server(self.handle, "127.0.0.1", self.port)
            async with self.server:
                await self.server.serve_forever()

        threading.Thread(target=lambda: loop.run_until_complete(main()), daemon=True).start()
        time.sleep(0.2)


def test_qualisys_backend_against_a_qtm_rt_stand_in_on_loopback():
    c, s = np.cos(0.3), np.sin(0.3)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    frames = [{"base": ([0, 0, 0], np.eye(3)), "tip": ([10.0, 20.0, -250.0], Rz), "mid": ([0, 0, -125.0], np.eye(3))}
              for _ in range(20)]
    frames += [{"base": ([0, 0, 0], np.eye(3)), "tip": None, "mid": ([0, 0, -125.0], np.eye(3))}] * 30
    qtm = QTMStandIn(["base", "mid", "tip", "other"], frames)
    qtm.serve()
    mocap = QualisysMotionCapture("127.0.0.1", qtm.port, bodies=("base", "mid", "tip"), frequency=100)
    mocap.start()
    try:
        seen_valid = None
        for _ in range(200):
            number, poses = mocap.latest()
            if number >= 0 and poses["tip"].valid and seen_valid is None:
                seen_valid = poses
            if number >= 25:
                break
            time.sleep(0.01)
        assert seen_valid is not None
        np.testing.assert_allclose(seen_valid["tip"].position, [0.01, 0.02, -0.25], atol=1e-6)  # mm -> m
        np.testing.assert_allclose(seen_valid["tip"].quaternion, [np.cos(0.15), 0, 0, np.sin(0.15)], atol=1e-5)
        assert number >= 25 and not poses["tip"].valid and poses["mid"].valid  # a lost body arrives as NaN
        assert any(cmd.startswith("streamframes frequency:100 6d") for cmd in qtm.commands)
    finally:
        mocap.close()
    with pytest.raises(ConnectionError, match="no 6DoF bodies"):
        QualisysMotionCapture("127.0.0.1", qtm.port, bodies=("base", "elbow")).start()


# ------------------------------------------------------------------------------------ twin env
@pytest.fixture(scope="module")
def env():
    e = SoPrAEnv("sim", install_signal_handlers=False)
    yield e
    e.close()


def test_twin_specs_and_table_s4_layout(env):
    from torchrl.envs.utils import check_env_specs

    check_env_specs(env)
    lay = {k: (v.start, v.stop) for k, v in sopra_layout().items()}
    assert lay == {"tip_position": (0, 3), "tip_orientation": (3, 7), "mid_position": (7, 10),
                   "mid_orientation": (10, 14), "tip_velocity": (14, 17), "tip_angular_velocity": (17, 20),
                   "mid_velocity": (20, 23), "mid_angular_velocity": (23, 26), "previous_pressures": (26, 32)}
    env.set_seed(0)
    td = env.reset()
    obs = td["observation"].numpy()
    np.testing.assert_allclose(obs[0:3], [0, 0, -0.25], atol=3e-3)  # tip 25 cm below the base ring
    np.testing.assert_allclose(obs[7:10], [0, 0, -0.125], atol=3e-3)
    for q in (obs[3:7], obs[10:14]):
        assert abs(np.linalg.norm(q) - 1) < 1e-5 and q[0] > 0.99
    np.testing.assert_allclose(obs[26:32], 0)
    a = torch.tensor([1.0, 0, 0, 0, 0, 0.5])
    for _ in range(10):
        td = env.step(TensorDict({"action": a}, []))["next"]
    obs = td["observation"].numpy()
    np.testing.assert_allclose(obs[26:32], env.safety.last_command / env.limits.p_max, atol=1e-6)
    assert obs[26] == pytest.approx(1.0)  # 10 x 50 mbar, capped at p_max = 400
    assert obs[31] == pytest.approx(250 / 400)  # 10 x 25 mbar
    assert np.linalg.norm(obs[14:17]) > 1e-3  # the tip moves
    # a controller emitting garbage is a safety fault: vented, latched, the episode ends
    td = env.step(TensorDict({"action": torch.full((6,), 2.0)}, []))["next"]
    assert bool(td["safety_fault"]) and bool(td["done"]) and "outside the action space" in env.safety.latched
    assert (env.safety.last_command == 0).all()


@pytest.mark.parametrize("task", ["reach-close", "reach-far"])
def test_twin_targets_reachable(task):
    e = SoPrAEnv("sim", task=task, install_signal_handlers=False, max_steps=60)
    e.set_seed(0)
    e.reset()
    goal = SOPRA_TARGET_PRESSURES[task]
    best = np.inf
    for _ in range(60):  # scripted: ramp the pressures to those that define the target
        delta = np.clip((goal - e.safety.last_command) / e.max_step, -1, 1)
        td = e.step(TensorDict({"action": torch.as_tensor(delta, dtype=torch.float32)}, []))["next"]
        best = min(best, float(np.linalg.norm(td["observation"][:3].numpy() - SOPRA_TARGETS[task])))
    assert best < 0.003, best  # within 3 mm (mocap noise 0.2 mm)
    e.close()


def test_reach_any_targets_are_fixed_per_episode_and_reachable():
    from torchrl_softae.tasks.sopra import tasks

    family = tasks()["reach-any"]
    a, b = family.for_episode(3), family.for_episode(4)
    assert a.params == family.for_episode(3).params  # every method sees the same i-th target
    assert a.params != b.params
    for task in (a, b):  # a settled tip under capped pressures: below the base, within the arm's reach
        target = np.asarray(task.params["target"])
        assert -0.30 < target[2] < -0.15 and np.linalg.norm(target[:2]) < 0.12, target


def test_reference_paths_have_the_stated_size():
    from torchrl_softae.tasks.sopra import reference_path

    center = np.array([0.01, -0.02, -0.25])
    square = reference_path("square", center)
    assert square.shape == (80, 3) and np.allclose(square[:, 2], -0.25)
    assert np.allclose(square[0], square[-1]) and np.allclose(np.ptp(square[:, :2], axis=0), 0.03)
    assert np.allclose(square.mean(axis=0)[:2], center[:2], atol=1e-3)
    lemniscate = reference_path("lemniscate", center)
    assert np.allclose(np.ptp(lemniscate[:, :2], axis=0), [0.04, 0.02], atol=1e-3)
    with pytest.raises(ValueError, match="shape 'circle'"):
        reference_path("circle", center)


def test_tracking_moves_the_target_every_step_and_scores_each_step_against_its_point():
    from torchrl_softae.envs.robots.reach import reach_reward
    from torchrl_softae.pipeline.evaluate import episode_seed, task_rollouts
    from torchrl_softae.tasks.sopra import reference_path, tasks

    def ramp(real, seed, task):  # pressures up in chambers 0 and 3: the tip leaves the rest point
        return lambda td: td.set("action", torch.tensor([0.5, 0, 0, 0.5, 0, 0]))

    family = tasks()["track-square"]
    res = task_rollouts("SoPrA-v0", family, 1, 0, ramp)
    metrics = res["metrics"][0]
    tips = torch.tensor(metrics["tips"])
    assert tips.shape == (79, 3)
    path = torch.as_tensor(reference_path("square", metrics["target_center"]), dtype=torch.float32)
    # reward of step t against point t + 1 (the one the action should reach); an off-by-one in
    # advancing the target scores a different sum
    expected = reach_reward((tips - path[1:]).norm(dim=-1)).sum()
    assert res["returns"][0] == pytest.approx(float(expected), rel=1e-5)
    assert float(reach_reward((tips - path[:-1]).norm(dim=-1)).sum()) != pytest.approx(res["returns"][0], rel=1e-3)
    horizontal = ((tips[:, :2] - path[1:, :2]).norm(dim=-1) * 1e3)
    assert metrics["mean_error_mm"] == pytest.approx(float(horizontal.mean()), rel=1e-5)
    assert family.for_episode(episode_seed(0, 0)).params["center"] == metrics["target_center"]


def test_a_family_of_targets_is_no_training_task():
    from torchrl_softae.pipeline.config import ConfigError, make_config

    with pytest.raises(ConfigError, match="'track-square' is a family of targets .*: hucrl explores on one fixed"):
        make_config("SoPrA-v0", "hucrl", task="track-square")


def test_lost_body_vents_and_ends_episode_and_overruns_are_reported():
    e = SoPrAEnv("sim", install_signal_handlers=False, control_period=0.05)
    e.set_seed(0)
    e.reset()
    td = e.step(TensorDict({"action": torch.ones(6)}, []))["next"]
    assert not td["safety_fault"] and not td["overrun"]
    time.sleep(0.08)  # a policy slower than the control period
    td = e.step(TensorDict({"action": torch.ones(6)}, []))["next"]
    assert td["overrun"] and e.timing["overruns"] == 1
    e.twin.p.mocap_dropout = 1.0  # every body lost from now on
    vents = e.safety.vent_count
    for _ in range(5):
        td = e.step(TensorDict({"action": torch.ones(6)}, []))["next"]
        if td["safety_fault"]:
            break
    assert td["safety_fault"] and td["terminated"] and e.safety.vent_count >= vents + 1  # fault, then episode end
    assert "lost bodies" in e.safety.faults[-1]
    assert (e.twin.read_pressures() >= 0).all() and (e.safety.last_command == 0).all()
    e.close()


def test_pipeline_explores_the_twin(tmp_path):
    from torchrl_softae.pipeline.cli import main
    from torchrl_softae.pipeline.runs import RunDir

    # two episodes: the env (and its safety layer, which never re-arms once closed) lives across them
    argv = ["explore", "--env", "SoPrA-v0", "--method", "softae", "--episodes", "2", "--episode-length", "10",
            "--run-dir", str(tmp_path), "--wandb", "disabled", "--quiet", "--set", "heldout_size=100",
            "--set", "model.num_cells=32", "--set", "model.depth=2", "--set", "planner.num_candidates=10",
            "--set", "planner.top_k=2", "--set", "planner.optim_steps=1", "--set", "train.epochs=2"]
    assert main(argv) == 0
    state = RunDir(tmp_path).load()
    assert state["num_transitions"] == 20
    assert main(["evaluate", "--run-dir", str(tmp_path), "--task", "reach-close", "--episodes", "1", "--quiet"]) == 0
