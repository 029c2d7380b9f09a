"""Run directories: atomic checkpoints, the persistent replay buffer, logs. A killed run resumes.

Layout of a run dir::

    config.json          the ExploreConfig (validated against on resume)
    checkpoint.pt        last complete episode: model, optimizer, history (no RNG: episodes reseed
                         from (seed, episode); no planner state: each episode starts a fresh plan)
    replay_ep0007/       TorchRL ReplayBuffer.dumps() of all transitions up to that episode
    replay_scratch/      LazyMemmapStorage working files of the live buffer
    metrics.jsonl/.csv   one row per episode (rewritten from the checkpoint, so never ahead of it)
    heldout.pt           held-out transitions for the model-accuracy metric
    eval/TASK.json       zero-shot evaluation results
    plots/*.png          coverage heatmap, curves, bars
    wandb/               offline W&B run (``wandb sync`` it later)

Ordering makes every state consistent: the replay dump of episode n is written to a new
directory, then the checkpoint that names it replaces the old one atomically (``os.replace``),
then older dumps are deleted. A kill at any point leaves the previous checkpoint and its dump.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import shutil
import signal
from pathlib import Path

import torch
from torchrl.data import LazyMemmapStorage, ReplayBuffer

from torchrl_softae.pipeline.guards import critical

__all__ = ["CheckpointError", "RunDir", "atomic_write_text", "atomic_torch_save", "atomic_savefig", "run_dirs_below", "POLICIES_DIR",
           "exit_once_after", "signal_once_at", "SIGNAL_ENV", "REFERENCES_FILE"]

CHECKPOINT_FORMAT = 1


def _atomic_write(path: Path, write) -> None:
    """``write(file)`` into a temporary sibling, flush it to disk, then ``os.replace`` it onto
    ``path``: a reader (or a resumed run) sees the old file or the new one, never half of one. A
    failed write (a full disk) removes the temporary file and raises ``OSError`` naming ``path``."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        cause = _os_error(e)
        if cause is None:
            raise
        raise OSError(cause.errno, cause.strerror, str(path)) from e


def _os_error(e: BaseException) -> OSError | None:
    """``e``, or the ``OSError`` it was raised while handling: ``torch.save`` turns a failed write
    into a ``RuntimeError`` of its zip writer when it closes the file."""
    while e is not None:
        if isinstance(e, OSError):
            return e
        e = e.__cause__ or e.__context__
    return None


def atomic_write_text(path: Path, text: str) -> None:
    _atomic_write(path, lambda f: f.write(text.encode()))


def atomic_torch_save(obj, path: Path) -> None:
    _atomic_write(path, lambda f: torch.save(obj, f))


def atomic_savefig(fig, path: Path, **kwargs) -> None:
    """``fig.savefig`` through :func:`_atomic_write`: a failed write never replaces a good plot."""
    path = Path(path)
    _atomic_write(path, lambda f: fig.savefig(f, format=path.suffix.lstrip(".") or "png", **kwargs))


#: inside a run dir: the task policies trained on its model (``softae policy``), not runs themselves
POLICIES_DIR = "policies"
#: the model-free references of an evaluation, ``RUN/eval/references.json`` (evaluate.write_references)
REFERENCES_FILE = "references.json"


def run_dirs_below(folder: str | os.PathLike, marker: str = "config.json") -> list[Path]:
    """The run dirs below ``folder`` (folders holding ``marker``), without the task-policy dirs
    that ``softae policy`` writes inside runs (``RUN/policies/...``)."""
    folder = Path(folder)
    return sorted(p.parent for p in folder.rglob(marker)
                  if POLICIES_DIR not in p.relative_to(folder).parts[:-1])


def exit_once_after(env_var: str, count: int, folder: Path, what: str) -> None:
    """Test hook for kill-and-resume tests: when ``$env_var`` is ``K`` (or ``K:NAME``, only folders
    whose name contains NAME) and ``count == K``, die at once (``os._exit(17)``, no cleanup, like
    a kill), once per folder (a marker file remembers it)."""
    spec = os.environ.get(env_var)
    if not spec:
        return
    k, _, name = spec.partition(":")
    marker = folder / ".injected_exit"
    if count == int(k) and name in folder.name and not marker.exists():
        marker.write_text(f"killed after {what} {count}\n")
        os._exit(17)


#: test hook (:func:`signal_once_at`): ``SOFTAE_SIGNAL_AT=POINT:K`` sends this process SIGTERM at
#: ``POINT`` of episode ``K`` (1-based), once per run dir: ``collect`` (the episode's data collected,
#: not yet stored), ``train`` (stored, the model not yet trained), ``checkpoint`` (the replay dump
#: written, the checkpoint not yet replaced)
SIGNAL_ENV = "SOFTAE_SIGNAL_AT"


def signal_once_at(point: str, count: int, folder: Path) -> None:
    """Test hook for stop-and-resume tests: SIGTERM to this process where :data:`SIGNAL_ENV` says."""
    spec = os.environ.get(SIGNAL_ENV)
    if not spec:
        return
    where, _, k = spec.partition(":")
    marker = folder / ".injected_signal"
    if where == point and count == int(k) and not marker.exists():
        marker.write_text(f"SIGTERM at {point} of episode {count}\n")
        os.kill(os.getpid(), signal.SIGTERM)


class CheckpointError(RuntimeError):
    """A checkpoint is unreadable or does not belong to this configuration."""


class RunDir:
    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.saved_episodes = 0  # complete episodes on disk, as far as this object has loaded or saved them

    # ------------------------------------------------------------------ paths
    @property
    def config_path(self) -> Path:
        return self.path / "config.json"

    @property
    def checkpoint_path(self) -> Path:
        return self.path / "checkpoint.pt"

    @property
    def heldout_path(self) -> Path:
        return self.path / "heldout.pt"

    def replay_dump(self, episode: int) -> Path:
        return self.path / f"replay_ep{episode:04d}"

    @property
    def plots(self) -> Path:
        p = self.path / "plots"
        p.mkdir(parents=True, exist_ok=True)
        return p

    @property
    def eval_dir(self) -> Path:
        p = self.path / "eval"
        p.mkdir(parents=True, exist_ok=True)
        return p

    def exists(self) -> bool:
        return self.checkpoint_path.exists()

    # ------------------------------------------------------------------ config
    def read_config(self) -> dict | None:
        if not self.config_path.exists():
            return None
        try:
            return json.loads(self.config_path.read_text())
        except json.JSONDecodeError as e:
            raise CheckpointError(f"{self.config_path} is not valid JSON ({e}); it is corrupt") from None

    def write_json(self, path: Path, obj) -> None:
        atomic_write_text(path, json.dumps(obj, indent=1, sort_keys=True, default=float))

    # ------------------------------------------------------------------ replay buffer
    def new_replay_buffer(self, capacity: int) -> ReplayBuffer:
        scratch = self.path / "replay_scratch"
        shutil.rmtree(scratch, ignore_errors=True)
        return ReplayBuffer(storage=LazyMemmapStorage(capacity, scratch_dir=str(scratch)), batch_size=64)

    def load_replay_buffer(self, state: dict, capacity: int | None = None) -> ReplayBuffer:
        """The replay buffer a checkpoint ``state`` names, grown to ``capacity`` if that is larger."""
        rb = self._load_dump(self.new_replay_buffer(state["replay_capacity"]), state)
        if capacity is not None and capacity > state["replay_capacity"]:  # the run was extended
            data = rb.storage[: len(rb)]
            rb = self.new_replay_buffer(capacity)
            rb.extend(data)
        return rb

    def read_transitions(self, state: dict):
        """The transitions of the replay dump a checkpoint ``state`` names, read into memory: the
        run's own working files are not touched, so a run that is still exploring is safe."""
        from torchrl.data import LazyTensorStorage

        rb = self._load_dump(ReplayBuffer(storage=LazyTensorStorage(state["replay_capacity"])), state)
        return rb.storage[: len(rb)]

    def _load_dump(self, rb: ReplayBuffer, state: dict) -> ReplayBuffer:
        dump, expected = self.replay_dump(state["episode"]), state["num_transitions"]
        if not dump.exists():
            raise CheckpointError(f"checkpoint names replay dump {dump}, which is missing: the run dir is corrupt")
        try:
            rb.loads(str(dump))
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(f"replay dump {dump} is unreadable ({type(e).__name__}: {e})") from None
        if len(rb) != expected:
            raise CheckpointError(f"replay dump {dump} holds {len(rb)} transitions, the checkpoint expects {expected}")
        return rb

    # ------------------------------------------------------------------ checkpoint
    def save(self, state: dict, rb: ReplayBuffer) -> None:
        """Checkpoint an episode: its replay dump into a new folder, then the checkpoint naming it
        (atomically), then the logs, then older dumps go. SIGTERM/SIGINT wait for the end
        (:func:`~torchrl_softae.pipeline.guards.critical`); a failed write (a full disk) removes
        what it began and leaves the previous checkpoint, its dump and the logs as they were."""
        with critical():
            episode = state["episode"]
            dump = self.replay_dump(episode)
            shutil.rmtree(dump, ignore_errors=True)
            try:
                rb.dumps(str(dump))
            except OSError as e:
                shutil.rmtree(dump, ignore_errors=True)
                raise OSError(e.errno, e.strerror, str(dump)) from e
            state = {**state, "format": CHECKPOINT_FORMAT, "num_transitions": len(rb), "replay_dump": dump.name,
                     "replay_capacity": rb.storage.max_size}
            signal_once_at("checkpoint", episode + 1, self.path)
            try:
                atomic_torch_save(state, self.checkpoint_path)
            except OSError:
                shutil.rmtree(dump, ignore_errors=True)  # the old checkpoint still names the old dump
                raise
            self.saved_episodes = episode + 1
            # the checkpoint names the new dump now: logs follow it (a failure here is caught up by
            # the next save or the resume, which rewrites them from the checkpoint)
            self.write_logs(state["history"])
            for old in self.path.glob("replay_ep*"):
                if old.name != dump.name:
                    shutil.rmtree(old, ignore_errors=True)

    def load(self) -> dict:
        try:
            state = torch.load(self.checkpoint_path, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(
                f"checkpoint {self.checkpoint_path} is corrupt or unreadable ({type(e).__name__}: {e}); "
                "delete it to restart the run from scratch, or use another --run-dir"
            ) from None
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise CheckpointError(f"{self.checkpoint_path} is not a torchrl_softae checkpoint (format {CHECKPOINT_FORMAT})")
        for key in ("episode", "config", "model", "history", "num_transitions", "replay_capacity"):
            if key not in state:
                raise CheckpointError(f"checkpoint {self.checkpoint_path} lacks {key!r}: it is corrupt")
        self.saved_episodes = state["episode"] + 1
        return state

    # ------------------------------------------------------------------ logs
    def write_logs(self, history: list[dict]) -> None:
        atomic_write_text(self.path / "metrics.jsonl", "".join(json.dumps(row, default=float) + "\n" for row in history))
        keys = sorted({k for row in history for k, v in row.items() if not isinstance(v, (dict, list))})
        buf = io.StringIO(newline="")
        w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for row in history:
            w.writerow({k: row.get(k, "") for k in keys})
        atomic_write_text(self.path / "metrics.csv", buf.getvalue())

    def history(self) -> list[dict]:
        p = self.path / "metrics.jsonl"
        if not p.exists():
            return []
        return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
