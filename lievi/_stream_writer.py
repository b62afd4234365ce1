"""Where a streamed batch (`lievi.stream_batch`) puts its output: the writer interface
(`AbstractStreamWriter`) and `NpyWriter`, NumPy files written in place."""

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
    """A chunk of bodies after its last finished segment, the chunk's rows leading: the
    state `g` `(b, n, n)`, `m` `(b, d)` it resumes from (at `steps_done·h`), and per body
    `result` (the first failure), `failed_step` (−1 if none), `total_newton_iterations`."""

    g: np.ndarray
    m: np.ndarray
    result: np.ndarray
    failed_step: np.ndarray
    total_newton_iterations: np.ndarray
    steps_done: int


@dataclasses.dataclass(frozen=True)
class StreamLayout:
    """A streamed run's output, `fields[name] = (shape, dtype)` (e.g. `"m": ((B, T, d),
    "float64")`), and the settings a resumed run must share with the run it continues:
    the layout's own and `run` (the system, integrator, `g0`, `m0`, `h`, options and
    lievi's version, as values or digests)."""

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
        """`ValueError` naming each setting that differs unless `stored` (the `settings()`
        found at `where`) is this run's."""
        settings = self.settings()
        run, stored_run = settings.pop("run"), dict(stored.get("run", {}))
        stored = {k: v for k, v in stored.items() if k != "run"}

        def short(value):  # a digest shown by its first hex digits
            text = str(value) if value is not None else "none"
            return text[:19] + "…" if text.startswith("sha256:") else text

        differ = [
            f"`{name}` ({short(there.get(name))} there, {short(now.get(name))} now)"
            for now, there in ((settings, stored), (run, stored_run))
            for name in sorted(set(now) | set(there))
            if now.get(name) != there.get(name)
        ]
        if differ:
            raise ValueError(
                f"`writer`: {where} holds another run; it differs in {', '.join(differ)}. "
                "Pass a new directory, or the arguments of that run to resume it."
            )


class AbstractStreamWriter(abc.ABC):
    """The interface of `lievi.stream_batch`'s `writer`: `open(layout)` once, per chunk
    `resume_state(chunk)`, after each finished segment `write(chunk, rows, saves, values,
    state)`, `finish()` once every chunk has reached the horizon, and `close()` in any
    case. A writer that resumes a stopped run returns each chunk's last `state` from
    `resume_state`; one that does not returns `None` (the chunk starts over)."""

    @abc.abstractmethod
    def open(self, layout: StreamLayout) -> None:
        """Create the storage for `layout`, or reopen a run's with the same layout (to
        resume it); a different layout is a `ValueError`."""

    @abc.abstractmethod
    def resume_state(self, chunk: int) -> ChunkState | None:
        """The state of `chunk` after its last finished segment, or `None`."""

    @abc.abstractmethod
    def write(
        self,
        chunk: int,
        rows: slice,
        saves: slice,
        values: dict[str, np.ndarray],
        state: ChunkState,
    ) -> None:
        """Store `values[name]`, the saves `saves` of the bodies `rows` (`(b, s, …)`), then
        `state`: once `write` returns the segment is finished; raise if anything could not
        be stored."""

    def finish(self) -> None:
        """Mark the run complete (before `close`; not when it stops early). Default: none."""
        return None

    @abc.abstractmethod
    def close(self) -> None:
        """Flush and release the storage."""


class NpyWriter(AbstractStreamWriter):
    """Write a streamed run to NumPy files in `directory`, in place: `g.npy` `(B, T,
    *element)`, `m.npy` `(B, T, *momentum)` as `simulate_batch` returns them, and per body
    `result.npy`, `failed_step.npy`, `total_newton_iterations.npy` (read them with
    `numpy.load(path, mmap_mode="r")`). Created at full size, the saves NaN and `result`
    `RESULTS.not_run` until a body's chunk reaches the horizon or fails;
    `complete.json` appears when the run is done. The resume state, `state/` (one file a
    chunk), is replaced atomically once the segment's saves are on the disk (`fsync`), so
    a stop at any point leaves each chunk at a finished segment; a write that fails or
    stores too few bytes raises `OSError`. `layout.json` records what defines the run:
    the same arguments and directory resume it, others are a `ValueError` naming what
    differs (docs/larger-than-memory.md).

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
        # A body still successful short of the horizon is reported `RESULTS.not_run`.
        unfinished = (state.result == RESULTS.successful) & (state.steps_done < self._n_steps)
        result = np.where(unfinished, RESULTS.not_run, state.result).astype(np.int32)
        summary = dict(state._asdict(), result=result)
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
    """Replace `path` by `data` atomically, on the disk on return (the rename flushed too)."""
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
    """An `.npy` file written in place by plain file writes, one contiguous block a body:
    not a memory map, whose written pages count as the writer's memory and whose failed
    writes are signals, not errors."""

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
        """All of `value`'s bytes at `position`: a short write (POSIX allows it) is
        continued, one that stores none or fails raises."""
        data = memoryview(np.ascontiguousarray(value)).cast("B")
        while data:
            try:
                written = os.pwrite(self.fd, data, position)
                if written <= 0:
                    raise OSError(errno.EIO, "nothing was stored")
            except OSError as error:
                raise OSError(
                    error.errno,
                    f"writing {self.path} failed at byte {position} ({error.strerror}); "
                    "the segment is not recorded as done. Free disk space (or raise the "
                    "quota or file-size limit) and call stream_batch again to resume.",
                ) from error
            data, position = data[written:], position + written

    def sync(self) -> None:
        os.fsync(self.fd)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
