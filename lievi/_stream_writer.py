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
import json
import os
import pathlib
from typing import NamedTuple

import numpy as np


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


@dataclasses.dataclass(frozen=True)
class StreamLayout:
    """The shape of a streamed run's output: `fields[name] = (shape, dtype)` of each saved
    field over the whole run (e.g. `"m": ((B, T, d), "float64")`), and the settings a
    resumed run must share with the run it continues."""

    fields: dict[str, tuple[tuple[int, ...], str]]
    batch: int
    n_steps: int
    save_every: int
    chunk_size: int
    segment_steps: int
    state_shapes: tuple[tuple[int, ...], tuple[int, ...]]  # one body's (g, m)
    dtype: str

    def n_chunks(self) -> int:
        return -(-self.batch // self.chunk_size)

    def settings(self) -> dict:
        """A JSON-able record of the layout."""
        record = dataclasses.asdict(self)
        record["fields"] = {k: [list(s), d] for k, (s, d) in self.fields.items()}
        record["state_shapes"] = [list(s) for s in self.state_shapes]
        return record


class AbstractStreamWriter(abc.ABC):
    """The interface of `lievi.stream_batch`'s `writer`.

    `stream_batch` calls `open(layout)` once, then for each chunk `resume_state(chunk)`,
    and after each finished segment `write(chunk, rows, saves, values, state)`. A writer
    that should resume a stopped run keeps the last `state` of each chunk and returns it
    from `resume_state`; one that does not returns `None` (the chunk starts over).
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
        then `state`: once `write` returns, the segment counts as finished."""

    @abc.abstractmethod
    def close(self) -> None:
        """Flush and release the storage (after the last chunk)."""


class NpyWriter(AbstractStreamWriter):
    """Write a streamed run to NumPy files in `directory`, in place: one `NAME.npy`
    per saved field with the shape of `simulate_batch`'s output (`g.npy`: `(B, T, n, n)`,
    `m.npy`: `(B, T, d)`), and per body `result.npy`, `failed_step.npy`,
    `total_newton_iterations.npy` (complete once the run is). Read them with
    `numpy.load(path, mmap_mode="r")`. The resume state lives in `directory/state/`, one
    file per chunk, replaced atomically after the chunk's saves of the segment are
    written, and `directory/layout.json` records the run's settings: calling
    `stream_batch` again with the same arguments and directory resumes each chunk from
    its last finished segment.

    **Arguments:**

    - `directory`: where to write (created if missing).
    """

    SUMMARY = ("result", "failed_step", "total_newton_iterations")

    def __init__(self, directory):
        self.directory = pathlib.Path(directory)
        self._files: dict[str, _NpyFile] = {}

    def _state_path(self, chunk: int) -> pathlib.Path:
        return self.directory / "state" / f"chunk{chunk:08d}.npz"

    def open(self, layout: StreamLayout) -> None:
        record = self.directory / "layout.json"
        settings = layout.settings()
        resume = record.exists()
        if resume and json.loads(record.read_text()) != settings:
            raise ValueError(
                f"`writer`: {self.directory} holds a run with other settings "
                f"({record.read_text()}); pass a new directory, or the same arguments to "
                "resume it."
            )
        (self.directory / "state").mkdir(parents=True, exist_ok=True)
        shapes = dict(layout.fields)
        shapes["result"] = ((layout.batch,), "int32")
        shapes["failed_step"] = ((layout.batch,), "int32")
        shapes["total_newton_iterations"] = ((layout.batch,), "int64")
        for name, (shape, dtype) in shapes.items():
            path = self.directory / f"{name}.npy"
            if not resume:
                # The header and a file of the full size (sparse: nothing is written yet).
                np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=tuple(shape))
            self._files[name] = _NpyFile(path)
        if not resume:
            record.write_text(json.dumps(settings))

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
        for name in self.SUMMARY:
            self._files[name].write(rows, None, getattr(state, name))
        for file in self._files.values():
            file.flush()
        # The state last, atomically: a run stopped before this line redoes the segment
        # (rewriting the same values); after it, it goes on from here.
        path = self._state_path(chunk)
        partial = path.with_suffix(".partial.npz")
        np.savez(partial, **state._asdict())
        os.replace(partial, path)

    def close(self) -> None:
        for file in self._files.values():
            file.close()
        self._files.clear()


class _NpyFile:
    """An `.npy` file written in place by plain file writes, one contiguous block a body.

    Not a memory map: the pages written to a map stay in the writing process's resident
    memory until the kernel reclaims them, so writing a file larger than memory through
    one would look (and, under a memory limit, count) as that much memory."""

    def __init__(self, path):
        header = np.load(path, mmap_mode="r")
        self.offset, self.shape, self.dtype = header.offset, header.shape, header.dtype
        del header
        self.file = open(path, "r+b")  # noqa: SIM115 (kept open across writes; `close`)

    def write(self, rows: slice, saves: slice | None, value) -> None:
        """`array[rows, saves] = value` (`saves=None`: `array[rows] = value`)."""
        value = np.ascontiguousarray(value, self.dtype)
        per_row = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        if saves is None:
            os.pwrite(self.file.fileno(), value.tobytes(), self.offset + rows.start * per_row)
            return
        per_save = per_row // self.shape[1]
        for i, row in enumerate(range(rows.start, rows.stop)):
            position = self.offset + row * per_row + saves.start * per_save
            os.pwrite(self.file.fileno(), value[i].tobytes(), position)

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()
