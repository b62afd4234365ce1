"""Where a streamed batch (`lievi.stream_batch`) puts its output: a writer.

A writer receives each chunk's saved steps segment by segment, as they finish, and keeps
the state a run resumes from (`ChunkState`: `(g, m)` after the chunk's last finished
segment, its step count, and the per-body result so far). `AbstractStreamWriter` is the
interface (subclass it to hand the steps to anything: a database, a network, a reduction
on the fly); `NpyWriter` writes NumPy `.npy` files in place, block by block, so that the
output may be far larger than memory.
"""

from __future__ import annotations

import abc
import dataclasses
import errno
import io
import json
import os
import pathlib
from typing import NamedTuple

import numpy as np

from ._results import RESULTS


class ChunkState(NamedTuple):
    """A chunk of bodies after its last finished segment, NumPy arrays with the chunk's
    rows leading: the state `g` `(b, n, n)`, `m` `(b, d)` it resumes from (at time
    `steps_done·h`), and the run so far per body: `result` (a `RESULTS` code, the first
    failure), `failed_step` (−1 if none) and `total_newton_iterations`."""

    g: np.ndarray
    m: np.ndarray
    result: np.ndarray
    failed_step: np.ndarray
    total_newton_iterations: np.ndarray
    steps_done: int

    def reported_result(self, n_steps: int) -> np.ndarray:
        """`result` as the output reports it: a body still successful that has not reached
        the horizon `n_steps` (its chunk's run stopped, or is still going) is
        `RESULTS.not_run`, not a success; a failure is final."""
        unfinished = (self.result == RESULTS.successful) & (self.steps_done < n_steps)
        return np.where(unfinished, RESULTS.not_run, self.result).astype(np.int32)


@dataclasses.dataclass(frozen=True)
class StreamLayout:
    """The shape of a streamed run's output: `fields[name] = (shape, dtype)` of each saved
    field over the whole run (e.g. `"m": ((B, T, d), "float64")`), and the settings a
    resumed run must share with the run it continues: the layout's own, and `run`, what
    else defines the run (`stream_batch` records the system, the integrator, `g0`, `m0`,
    `h`, the options and lievi's version, as values or digests)."""

    fields: dict[str, tuple[tuple[int, ...], str]]
    batch: int
    n_steps: int
    save_every: int
    chunk_size: int
    segment_steps: int
    state_shapes: tuple[tuple[int, ...], tuple[int, ...]]  # one body's (g, m)
    dtype: str
    run: dict[str, str] = dataclasses.field(default_factory=dict)

    def n_chunks(self) -> int:
        return -(-self.batch // self.chunk_size)

    def settings(self) -> dict:
        """A JSON-able record of the layout."""
        record = dataclasses.asdict(self)
        record["fields"] = {k: [list(s), d] for k, (s, d) in self.fields.items()}
        record["state_shapes"] = [list(s) for s in self.state_shapes]
        return record

    def check_resumes(self, stored: dict, where: str) -> None:
        """Raise `ValueError` unless `stored` (the `settings()` of the run found at
        `where`) is this run's: the message names each setting that differs."""
        settings = self.settings()
        run, stored_run = settings.pop("run"), dict(stored.get("run", {}))
        stored = {k: v for k, v in stored.items() if k != "run"}
        differ = [
            f"`{name}` ({_short(stored.get(name))} there, {_short(settings.get(name))} now)"
            for name in sorted(set(settings) | set(stored))
            if settings.get(name) != stored.get(name)
        ]
        differ += [
            f"`{name}` ({_short(stored_run.get(name))} there, {_short(run.get(name))} now)"
            for name in sorted(set(run) | set(stored_run))
            if run.get(name) != stored_run.get(name)
        ]
        if differ:
            raise ValueError(
                f"`writer`: {where} holds another run; it differs in {', '.join(differ)}. "
                "Pass a new directory, or the arguments of that run to resume it."
            )


def _short(value) -> str:
    """A setting as a message shows it: a digest by its first hex digits."""
    if value is None:
        return "none"
    if isinstance(value, str) and value.startswith("sha256:"):
        return value[:19] + "…"
    return str(value)


class AbstractStreamWriter(abc.ABC):
    """The interface of `lievi.stream_batch`'s `writer`.

    `stream_batch` calls `open(layout)` once, then for each chunk `resume_state(chunk)`,
    and after each finished segment `write(chunk, rows, saves, values, state)`; once
    every chunk has reached the horizon, `finish()`; in any case (also when the run
    stops on an error) `close()`. A writer that should resume a stopped run keeps the
    last `state` of each chunk and returns it from `resume_state`; one that does not
    returns `None` (the chunk starts over).
    """

    @abc.abstractmethod
    def open(self, layout: StreamLayout) -> None:
        """Create the storage for `layout`, or reopen the storage of a run with the same
        layout (to resume it); a different layout is a `ValueError`."""

    @abc.abstractmethod
    def resume_state(self, chunk: int) -> ChunkState | None:
        """The state of `chunk` after its last finished segment, or `None` if none has
        finished."""

    @abc.abstractmethod
    def write(
        self,
        chunk: int,
        rows: slice,
        saves: slice,
        values: dict[str, np.ndarray],
        state: ChunkState,
    ) -> None:
        """Store `values[name]`, the saves `saves` of the bodies `rows` (`(b, s, …)`), and
        then `state`: once `write` returns, the segment counts as finished. Raise if any
        of it could not be stored (the segment then does not count as finished)."""

    def finish(self) -> None:
        """Mark the run complete: every chunk has reached the horizon (called before
        `close`; not called when the run stops early). Does nothing by default."""
        return None

    @abc.abstractmethod
    def close(self) -> None:
        """Flush and release the storage (after the last chunk, or when the run stops)."""


class NpyWriter(AbstractStreamWriter):
    """Write a streamed run to NumPy files in `directory`, in place: one `NAME.npy`
    per saved field with the shape of `simulate_batch`'s output (`g.npy`: `(B, T, *element)`,
    `m.npy`: `(B, T, *momentum)`), and per body `result.npy`, `failed_step.npy`,
    `total_newton_iterations.npy`. Read them with `numpy.load(path, mmap_mode="r")`.

    The files are created at their full size, the saves NaN and `result` the code
    `RESULTS.not_run`, so a body that has not run (yet) reads as such, never as a success
    with zeros; a body's `result` becomes its own once its chunk reaches the horizon (or
    at its failure). `directory/complete.json` appears when the whole run is done.

    The resume state lives in `directory/state/`, one file per chunk, replaced
    atomically after the chunk's saves of the segment are written and flushed to the disk
    (`fsync`), so a stop at any point — a power cut included — leaves each chunk at a
    finished segment. A write that fails or stores fewer bytes than asked (a full disk, a
    quota, a file-size limit) raises `OSError`, and its segment is not recorded as done.
    `directory/layout.json` records what defines the run (`StreamLayout.settings()`):
    calling `stream_batch` again with the same arguments and directory resumes each
    chunk from its last finished segment, and other arguments are a `ValueError` that
    names what differs.

    **Arguments:**

    - `directory`: where to write (created if missing).
    """

    SUMMARY = ("result", "failed_step", "total_newton_iterations")
    COMPLETE = "complete.json"

    def __init__(self, directory):
        self.directory = pathlib.Path(directory)
        self._files: dict[str, _NpyFile] = {}
        self._n_steps = 0

    def _state_path(self, chunk: int) -> pathlib.Path:
        return self.directory / "state" / f"chunk{chunk:08d}.npz"

    @staticmethod
    def _contents(layout: StreamLayout) -> dict[str, tuple[tuple[int, ...], str, float]]:
        """`name: (shape, dtype, value before anything is written)` of each file."""
        contents = {
            name: (tuple(shape), dtype, np.nan) for name, (shape, dtype) in layout.fields.items()
        }
        contents["result"] = ((layout.batch,), "int32", RESULTS.not_run)
        contents["failed_step"] = ((layout.batch,), "int32", -1)
        contents["total_newton_iterations"] = ((layout.batch,), "int64", 0)
        return contents

    def open(self, layout: StreamLayout) -> None:
        record = self.directory / "layout.json"
        self._n_steps = layout.n_steps
        if record.exists():
            layout.check_resumes(json.loads(record.read_text()), str(self.directory))
        else:
            self._create(layout, record)
        for name in self._contents(layout):
            self._files[name] = _NpyFile(self.directory / f"{name}.npy")

    def _create(self, layout: StreamLayout, record: pathlib.Path) -> None:
        state = self.directory / "state"
        state.mkdir(parents=True, exist_ok=True)
        # Without `layout.json` nothing here is a run's (its creation did not finish).
        for path in state.glob("chunk*.npz*"):
            path.unlink()
        (self.directory / self.COMPLETE).unlink(missing_ok=True)
        for name, (shape, dtype, value) in self._contents(layout).items():
            path = self.directory / f"{name}.npy"
            # The header, then every element written: the disk space is taken now (a disk
            # too small fails here, not hours into the run).
            np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
            file = _NpyFile(path)
            try:
                file.fill(value)
                file.sync()
            finally:
                file.close()
        # Last: a directory with `layout.json` holds a run whose files are all there.
        _replace_durably(record, json.dumps(layout.settings()).encode())

    def resume_state(self, chunk: int) -> ChunkState | None:
        path = self._state_path(chunk)
        if not path.exists():
            return None
        with np.load(path) as saved:
            state = {name: saved[name] for name in ChunkState._fields}
        state["steps_done"] = int(state["steps_done"])
        return ChunkState(**state)

    def write(self, chunk, rows, saves, values, state) -> None:
        for name, value in values.items():
            self._files[name].write(rows, saves, value)
        summary = dict(state._asdict(), result=state.reported_result(self._n_steps))
        for name in self.SUMMARY:
            self._files[name].write(rows, None, summary[name])
        for file in self._files.values():
            file.sync()
        # The state last, atomically and after the data are on the disk: a run stopped
        # before this line redoes the segment (rewriting the same values); after it, it
        # goes on from here.
        buffer = io.BytesIO()
        np.savez(buffer, **state._asdict())
        _replace_durably(self._state_path(chunk), buffer.getvalue())

    def finish(self) -> None:
        result = np.load(self.directory / "result.npy", mmap_mode="r")
        counts = {
            name: int(np.count_nonzero(result == code))
            for name, code in vars(RESULTS).items()
            if isinstance(code, int) and not name.startswith("_")
        }
        marker = {"bodies": int(result.shape[0]), "results": counts}
        _replace_durably(self.directory / self.COMPLETE, json.dumps(marker).encode())

    def close(self) -> None:
        for file in self._files.values():
            file.close()
        self._files.clear()


def _replace_durably(path: pathlib.Path, data: bytes) -> None:
    """Replace `path` by a file holding `data`, atomically, and on the disk on return:
    written beside it, flushed, renamed over it, and the rename flushed (the directory)."""
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as file:
        file.write(data)
        file.flush()
        os.fsync(file.fileno())
    os.replace(partial, path)
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


class _NpyFile:
    """An `.npy` file written in place by plain file writes, one contiguous block a body.

    Not a memory map: the pages written to a map stay in the writing process's resident
    memory until the kernel reclaims them, so writing a file larger than memory through
    one would look (and, under a memory limit, count) as that much memory. And a write
    through a map that the disk cannot take fails as a signal, not as an error here."""

    _BLOCK = 1 << 22  # bytes of the blocks `fill` writes

    def __init__(self, path):
        self.path = pathlib.Path(path)
        header = np.load(path, mmap_mode="r")
        self.offset, self.shape, self.dtype = header.offset, header.shape, header.dtype
        del header
        self.fd = os.open(path, os.O_RDWR)

    def write(self, rows: slice, saves: slice | None, value) -> None:
        """`array[rows, saves] = value` (`saves=None`: `array[rows] = value`)."""
        value = np.ascontiguousarray(value, self.dtype)
        per_row = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        if saves is None:
            self._write(value, self.offset + rows.start * per_row)
            return
        per_save = per_row // self.shape[1]
        for i, row in enumerate(range(rows.start, rows.stop)):
            self._write(value[i], self.offset + row * per_row + saves.start * per_save)

    def fill(self, value) -> None:
        """Every element set to `value`, a block at a time."""
        size = int(np.prod(self.shape, dtype=np.int64))
        block = np.full(min(size, max(1, self._BLOCK // self.dtype.itemsize)), value, self.dtype)
        for start in range(0, size, block.size):
            self._write(block[: size - start], self.offset + start * self.dtype.itemsize)

    def _write(self, value: np.ndarray, position: int) -> None:
        """Write all of `value`'s bytes at `position`. A write may store fewer bytes than
        asked (POSIX allows it): the rest is written again, and a write that stores none
        or fails — a full disk, a quota, a file-size limit — raises."""
        data = memoryview(np.ascontiguousarray(value)).cast("B")
        while data:
            try:
                written = os.pwrite(self.fd, data, position)
            except OSError as error:
                raise OSError(
                    error.errno,
                    f"writing {self.path} failed at byte {position} ({error.strerror}); "
                    "the segment is not recorded as done. Free disk space (or raise the "
                    "quota or file-size limit) and call stream_batch again to resume.",
                ) from error
            if written <= 0:
                raise OSError(
                    errno.EIO,
                    f"writing {self.path} stored nothing at byte {position}; the segment "
                    "is not recorded as done. Check the disk and call stream_batch again "
                    "to resume.",
                )
            data, position = data[written:], position + written

    def sync(self) -> None:
        """The bytes written so far, on the disk (`fsync`)."""
        os.fsync(self.fd)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
