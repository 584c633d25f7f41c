"""Resume checkpoints off the machine: a training step killed on one node resumes on another.

The trainer keeps its resumable checkpoints in the step's local run dir (capvector.tasks.runtime.workspace
`Workspace.run_dir`, under the machine's cache for a remote home). Where a shared scratch URL is
configured, each checkpoint the trainer saves is also copied to `<scratch>/<content key>/`, and a run
dir with no checkpoint as new is filled from there before training starts, so the trainer's own exact
resume (capvector.core.training.trainer) takes over on any machine, bit for bit as an uninterrupted run.

The scratch URL (`scratch_url`): `CAPVECTOR_SCRATCH` when set (any fsspec URL, also for a local home:
a path every node sees, an `s3://` prefix); otherwise `<home>/scratch` for a home on a remote
filesystem, beside the content-addressed `store/`, never inside it; none for a local home.

Layout of one run's folder::

    step_XXXXXXXX/{policy.safetensors, aux.safetensors, trainer_state.pt, train_config.json,
                   loss_curve.jsonl}       the newest checkpoint and the loss curve up to it
    snapshots/step_XXXXXXXX.safetensors  the kept snapshots up to it (each written once; with a LoRA-SP
                                         run's adapter files beside each, step_XXXXXXXX.adapter_*)
    checkpoint.json                       {"step", "files": {path: size}}: written last

A reader never takes a half-written checkpoint for a whole one: the files go first, `checkpoint.json`
naming them (with their sizes) last, and the folder of the previous checkpoint is removed only after
it. A restore checks every named file's size; whatever it cannot fetch is left out (one warning line)
and the run starts from what the local run dir has. A copy that fails does not stop training (one
warning line: that checkpoint is only local). The folder is removed when the step's artifact is
registered (`Workspace.finish_run_dir`).
"""

from __future__ import annotations

import json
import os
import posixpath
import re
import shutil
from pathlib import Path
from typing import Any

from capvector.artifacts.home import filesystem, is_local

SCRATCH_ENV = "CAPVECTOR_SCRATCH"
MANIFEST = "checkpoint.json"
CURVE = "loss_curve.jsonl"
_STEP = re.compile(r"^step_(\d{8})$")


def scratch_url(home: str) -> str | None:
    """Where resume checkpoints are copied for `home`: CAPVECTOR_SCRATCH, else `<home>/scratch` for a
    remote home, else None (checkpoints stay on the machine)."""
    configured = os.environ.get(SCRATCH_ENV)
    if configured:
        return configured
    if is_local(str(home)):
        return None
    return posixpath.join(str(home), "scratch")


def _warn(line: str) -> None:
    from capvector.tasks.runtime.progress import emit

    emit(f"warning: {line}", always=True)


def _local_step(run_dir: Path) -> int:
    """The newest checkpoint step in a local run dir (0: none)."""
    root = run_dir / "checkpoints"
    steps = [int(m.group(1)) for p in root.glob("step_*") if (m := _STEP.match(p.name)) and p.is_dir()]
    return max(steps, default=0)


class CheckpointMirror:
    """The scratch folder of one training run (`<url>/<content key>/`)."""

    def __init__(self, url: str, key: str):
        self.fs, base = filesystem(url)
        self.root = posixpath.join(base.rstrip("/"), key)
        self.where = posixpath.join(url.rstrip("/"), key)

    def _p(self, *parts: str) -> str:
        return posixpath.join(self.root, *parts)

    def manifest(self) -> dict[str, Any] | None:
        """The newest complete checkpoint's manifest, or None (none yet, or unreadable)."""
        try:
            doc = json.loads(self.fs.cat_file(self._p(MANIFEST)))
        except (FileNotFoundError, ValueError):
            return None
        ok = isinstance(doc, dict) and isinstance(doc.get("step"), int) and isinstance(doc.get("files"), dict)
        return doc if ok else None

    def _put(self, local: Path, rel: str) -> None:
        remote = self._p(rel)
        self.fs.makedirs(posixpath.dirname(remote), exist_ok=True)
        self.fs.put_file(str(local), remote)

    def save(self, step: int, checkpoint: Path, run_dir: Path) -> None:
        """Copy checkpoint `step` (its folder), the loss curve and the snapshots up to it; never raises."""
        try:
            self._save(step, checkpoint, run_dir)
        except Exception as e:  # the checkpoint is still on this machine; training goes on
            _warn(f"checkpoint at step {step} not copied to {self.where}: {type(e).__name__}: {e}")

    def _save(self, step: int, checkpoint: Path, run_dir: Path) -> None:
        previous = self.manifest()
        if previous is not None and previous["step"] == step:
            return  # already there, whole (a run resumed at this very checkpoint)
        name = checkpoint.name
        files: dict[str, int] = {}
        for f in sorted(checkpoint.iterdir()):
            self._put(f, f"{name}/{f.name}")
            files[f"{name}/{f.name}"] = f.stat().st_size
        self._put(run_dir / CURVE, f"{name}/{CURVE}")  # flushed up to `step` before the hook
        files[f"{name}/{CURVE}"] = (run_dir / CURVE).stat().st_size
        sent = (previous or {}).get("files", {})
        for snap in sorted((run_dir / "snapshots").glob("step_*")):  # weights, and a LoRA-SP run's adapter
            if not snap.is_file() or int(snap.name[5:13]) > step:
                continue
            rel = f"snapshots/{snap.name}"
            size = snap.stat().st_size
            if sent.get(rel) != size:  # snapshots never change: each is sent once
                self._put(snap, rel)
            files[rel] = size
        self.fs.pipe_file(self._p(MANIFEST), json.dumps({"step": step, "files": files}).encode())
        self.fs.invalidate_cache(self.root)
        for entry in self.fs.ls(self.root, detail=False):
            match = _STEP.match(posixpath.basename(entry.rstrip("/")))
            if match and int(match.group(1)) != step:
                self.fs.rm(entry, recursive=True)

    def restore(self, run_dir: Path) -> int:
        """Fetch the newest complete checkpoint into `run_dir` when it is newer than any checkpoint
        there; returns its step (0: nothing fetched). Never raises: a failed fetch leaves the run dir
        as it was, with one warning line."""
        manifest = self.manifest()
        if manifest is None or manifest["step"] <= _local_step(run_dir):
            return 0
        step = manifest["step"]
        name = f"step_{step:08d}"
        incoming = run_dir / "checkpoints" / f".fetch-{name}"
        shutil.rmtree(incoming, ignore_errors=True)
        try:
            self._fetch(manifest, name, incoming, run_dir)
        except Exception as e:
            _warn(f"checkpoint at step {step} not fetched from {self.where}: {type(e).__name__}: {e}")
            return 0
        finally:
            shutil.rmtree(incoming, ignore_errors=True)
        return step

    def _fetch(self, manifest: dict[str, Any], name: str, incoming: Path, run_dir: Path) -> None:
        incoming.mkdir(parents=True)
        snapshots: list[tuple[Path, Path]] = []
        for rel, size in manifest["files"].items():
            folder, _, filename = rel.partition("/")
            if "/" in filename or filename in ("", ".", ".."):
                raise ValueError(f"{MANIFEST} names {rel!r}, not a file of a checkpoint or snapshot")
            if folder == "snapshots":
                if (run_dir / rel).is_file():
                    continue
                target = incoming / "snapshots" / filename
                snapshots.append((target, run_dir / rel))
            elif folder == name:
                target = incoming / filename
            else:
                raise ValueError(f"{MANIFEST} names {rel!r}, outside checkpoint {name}")
            target.parent.mkdir(parents=True, exist_ok=True)
            self.fs.get_file(self._p(rel), str(target))
            if target.stat().st_size != size:
                raise OSError(f"{rel}: {target.stat().st_size} bytes, {MANIFEST} says {size}")
        # whole: move it in, the checkpoint folder last (the trainer resumes only from a checkpoint)
        for target, final in snapshots:
            final.parent.mkdir(parents=True, exist_ok=True)
            os.replace(target, final)
        if snapshots:
            (incoming / "snapshots").rmdir()
        os.replace(incoming / CURVE, run_dir / CURVE)
        os.replace(incoming, run_dir / "checkpoints" / name)

    def clear(self) -> None:
        """Remove the run's scratch folder (its step is registered); never raises."""
        try:
            self.fs.invalidate_cache(self.root)
            if self.fs.exists(self.root):
                self.fs.rm(self.root, recursive=True)
        except Exception as e:
            _warn(f"scratch folder {self.where} not removed: {type(e).__name__}: {e}")
