"""Fixed-memory ring buffer of numpy records: a writer that never blocks, readers that never stop it.

One :class:`RingBuffer` holds ``capacity`` rows of a numpy structured dtype, allocated once.
A writer appends rows (overwriting the oldest when full); readers take chronological copies.

Contract (read this before sharing a buffer between threads)
-----------------------------------------------------------
* **One writer per buffer.** Appends are not serialised against each other: they must never run
  concurrently (in practice: one thread appends to a buffer). Two threads appending at once
  corrupt it; a cheap check raises ``RuntimeError`` when it catches them.
  Any number of reader threads may call :meth:`RingBuffer.snapshot` / :meth:`RingBuffer.window`
  / :meth:`RingBuffer.read` concurrently with the writer.
* **The writer never waits and never allocates storage.** An append assigns into the
  preallocated row and bumps two integer counters; no lock, no list, no new array that outlives
  the call. CPython still creates and frees a few small objects per call (the int counters,
  a ``np.frombuffer`` view of a ``bytes`` argument); ``tracemalloc`` shows zero net growth and a
  peak of a few hundred bytes over thousands of appends (see ``tests/test_recorder.py``).
* **Readers are lock-free (seqlock style).** The writer bumps ``_started`` before touching a slot
  and ``_done`` after. A reader reads ``_done``, copies, then reads ``_started``: a row whose slot a
  write may have touched during the copy is discarded. Those are always the *oldest* rows (the
  ones being overwritten), so instead of retrying until no write overlapped (which never happens
  on a full buffer under a 1 kHz writer) the reader drops exactly them and counts them as
  overwritten. It retries (up to 4 times) only when it lost more than half of what it copied,
  i.e. when the reader itself was stalled for most of the buffer's span.
  The Python GIL orders the counter updates; the numpy copy may run truly in parallel with the
  writer (numpy releases the GIL for large copies), which is why the validation is needed.

Byte blobs: a field of base type ``u1`` with a 1-D shape (``('raw', 'u1', (1180,))``) accepts
``bytes``/``bytearray``/``memoryview``/``uint8`` arrays up to its size; the tail is zeroed, and a
companion field ``<name>_len`` (``u4``), when the dtype has one, is filled with the length
automatically (callers never pass it). :func:`blob_fields` builds that pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ReadResult", "RingBuffer", "blob_fields"]


def blob_fields(name: str, size: int) -> list[tuple]:
    """Dtype fields for a fixed-size raw message slot: ``name`` (u1[size]) and ``name_len`` (u4)."""
    if size <= 0:
        raise ValueError(f"blob size must be positive, got {size}")
    return [(name, "u1", (int(size),)), (f"{name}_len", "u4")]


@dataclass(frozen=True)
class ReadResult:
    """A consistent chronological copy of part of a ring buffer.

    ``rows``: the copied records (oldest first). ``total_written``: rows appended up to the
    moment the copy was taken. ``overwritten``: rows lost to overwriting by then (including any
    the writer reached while the copy ran), so ``total_written - overwritten`` rows were
    available and ``rows`` is the subset that falls in the requested time window.
    """

    rows: np.ndarray
    total_written: int
    overwritten: int


_SCALAR, _ARRAY, _BLOB = 0, 1, 2
_MAX_RETRIES = 4


class RingBuffer:
    """Preallocated ring of ``capacity`` records of ``dtype``; see the module docstring."""

    def __init__(self, dtype: np.dtype | list, capacity: int):
        dtype = np.dtype(dtype)
        if dtype.names is None:
            raise ValueError("RingBuffer needs a structured dtype (named fields)")
        if int(capacity) != capacity or capacity <= 0:
            raise ValueError(f"capacity must be a positive integer, got {capacity!r}")
        if dtype.hasobject:
            raise ValueError("RingBuffer dtype must not hold Python objects")
        self.dtype = dtype
        self.capacity = int(capacity)
        self._buf = np.zeros(self.capacity, dtype)
        self._started = 0  # writes begun (bumped before a slot is touched)
        self._done = 0  # writes completed (bumped after)
        self._floor = 0  # absolute index of the oldest row not lost to a failed append

        auto_len = set()
        plan = []
        for name in dtype.names:
            fdt = dtype.fields[name][0]
            base, shape = fdt.base, fdt.shape
            if base == np.uint8 and len(shape) == 1:
                len_name = f"{name}_len"
                len_col = None
                if len_name in dtype.names:
                    if dtype.fields[len_name][0] != np.dtype("u4"):
                        raise ValueError(f"{len_name} must be u4")
                    auto_len.add(len_name)
                    len_col = self._buf[len_name]
                plan.append((name, _BLOB, self._buf[name], shape[0], len_col))
            elif shape == ():
                plan.append((name, _SCALAR, self._buf[name], 0, None))
            else:
                plan.append((name, _ARRAY, self._buf[name], 0, None))
        # Fields the caller passes, in dtype order (automatic *_len fields excluded).
        self._plan = tuple(p for p in plan if p[0] not in auto_len)
        self.field_names: tuple[str, ...] = tuple(p[0] for p in self._plan)
        self._n_fields = len(self._plan)
        self._whole_row = all(p[1] != _BLOB for p in self._plan)

    # ---------------------------------------------------------------- writer side

    @property
    def total_written(self) -> int:
        """Rows appended so far (completed appends)."""
        return self._done

    @property
    def overwritten(self) -> int:
        """Rows no longer held: overwritten by newer ones (or lost to a failed append)."""
        return max(self._done - self.capacity, self._floor, 0)

    def __len__(self) -> int:
        return self._done - self.overwritten

    @property
    def nbytes(self) -> int:
        """Bytes of row storage (fixed at construction)."""
        return self._buf.nbytes

    def append(self, **fields) -> None:
        """Append one row given every field by name (``*_len`` of blobs excluded). Never blocks."""
        if len(fields) != self._n_fields:
            missing = set(self.field_names) - set(fields)
            extra = set(fields) - set(self.field_names)
            raise ValueError(f"append needs exactly the fields {self.field_names}; "
                             f"missing {sorted(missing)}, unknown {sorted(extra)}")
        i, slot = self._begin()
        try:
            for name, kind, col, size, len_col in self._plan:
                value = fields[name]
                if kind == _BLOB:
                    self._put_blob(col, len_col, slot, size, value)
                else:
                    col[slot] = value
        except KeyError as exc:
            self._abort(i)
            raise ValueError(f"unknown field in append: {sorted(set(fields) - set(self.field_names))}"
                             ) from exc
        except BaseException:
            self._abort(i)
            raise
        self._commit(i)

    def append_row(self, *values) -> None:
        """Append one row given its fields positionally, in :attr:`field_names` order."""
        if len(values) != self._n_fields:
            raise ValueError(f"append_row needs {self._n_fields} values {self.field_names}, "
                             f"got {len(values)}")
        i, slot = self._begin()
        try:
            if self._whole_row:  # no blob: numpy assigns the tuple field by field, in C
                self._buf[slot] = values
            else:
                self._fill(slot, values)
        except BaseException:
            self._abort(i)
            raise
        self._commit(i)

    def _fill(self, slot: int, values) -> None:
        for (_name, kind, col, size, len_col), value in zip(self._plan, values):
            if kind == _BLOB:
                self._put_blob(col, len_col, slot, size, value)
            else:
                col[slot] = value

    def write_from(self, record) -> None:
        """Append a record that already has this buffer's dtype (a ``np.void`` or 1-row array)."""
        if getattr(record, "dtype", None) != self.dtype:
            raise ValueError("write_from needs a record of exactly this buffer's dtype")
        if isinstance(record, np.ndarray):
            if record.shape not in ((), (1,)):
                raise ValueError(f"write_from takes one record, got shape {record.shape}")
            record = record.reshape(())[()]
        i, slot = self._begin()
        self._buf[slot] = record
        self._commit(i)

    def _begin(self) -> tuple[int, int]:
        i = self._started
        self._started = i + 1
        return i, i % self.capacity

    def _commit(self, i: int) -> None:
        if self._started != i + 1:
            raise RuntimeError("RingBuffer written by two threads at once (one writer per buffer)")
        self._done = i + 1

    def _abort(self, i: int) -> None:
        # The slot may be half written: the row it held (absolute index i - capacity) is lost.
        # Raise the floor first, then give the index back, so a reader never trusts that slot.
        self._floor = max(self._floor, i - self.capacity + 1)
        self._started = i

    @staticmethod
    def _put_blob(col, len_col, slot, size, value) -> None:
        data = value if isinstance(value, np.ndarray) else np.frombuffer(value, np.uint8)
        n = data.shape[0] if data.ndim == 1 else -1
        if n < 0 or n > size or data.dtype != np.uint8:
            raise ValueError(f"blob must be at most {size} bytes (1-D uint8), got {data.shape} "
                             f"{data.dtype}")
        if n == size:
            col[slot] = data
        else:
            col[slot, :n] = data
            col[slot, n:] = 0
        if len_col is not None:
            len_col[slot] = n

    # ---------------------------------------------------------------- reader side

    def read(self, t0_ns: int | None = None, t1_ns: int | None = None,
             time_field: str = "t_host_ns") -> ReadResult:
        """Consistent chronological copy of the rows with ``t0_ns <= row[time_field] < t1_ns``.

        ``None`` leaves that end open; with both ``None`` every held row is returned. Safe to
        call from any thread while the (single) writer appends; never blocks the writer.
        """
        if (t0_ns is not None or t1_ns is not None) and time_field not in self.dtype.names:
            raise ValueError(f"no time field {time_field!r} in {self.dtype.names}")
        for _ in range(_MAX_RETRIES):
            res, dropped, copied = self._read_once(t0_ns, t1_ns, time_field)
            # Losing a few of the oldest rows to a writer that laps them is normal on a full
            # ring; losing most of the copy means this reader was stalled (GIL switch, swap):
            # take the copy again rather than hand back a gutted history.
            if 2 * dropped <= copied:
                break
        return res

    def _read_once(self, t0_ns, t1_ns, time_field) -> tuple[ReadResult, int, int]:
        cap = self.capacity
        done = self._done
        lo = max(done - cap, self._floor, 0)
        if t0_ns is None and t1_ns is None:
            rows = self._copy_range(lo, done)
            keep_from = min(self._valid_lo(lo), done)
            return ReadResult(rows[keep_from - lo:], done, keep_from), keep_from - lo, done - lo

        times = self._copy_range(lo, done, self._buf[time_field])
        valid = min(self._valid_lo(lo), done)
        times = times[valid - lo:]
        mask = np.ones(times.shape[0], bool)
        if t0_ns is not None:
            mask &= times >= t0_ns
        if t1_ns is not None:
            mask &= times < t1_ns
        absolute = np.flatnonzero(mask) + valid
        rows = self._buf[absolute % cap]  # fancy indexing copies
        # Rows whose slot the writer reached during that copy are stale: drop them (the oldest).
        keep_from = min(self._valid_lo(valid), done)
        first = int(np.searchsorted(absolute, keep_from))
        return (ReadResult(rows[first:], done, keep_from), keep_from - lo,
                done - lo)

    def snapshot(self) -> np.ndarray:
        """Chronological copy of every held row (oldest first)."""
        return self.read().rows

    def window(self, t0_ns: int | None, t1_ns: int | None,
               time_field: str = "t_host_ns") -> np.ndarray:
        """Chronological copy of the rows with ``t0_ns <= row[time_field] < t1_ns`` (int ns)."""
        return self.read(t0_ns, t1_ns, time_field).rows

    def _valid_lo(self, lo: int) -> int:
        # Read after the copy: anything at or below started - capacity may have been rewritten.
        return max(lo, self._started - self.capacity, self._floor)

    def _copy_range(self, lo: int, hi: int, src: np.ndarray | None = None) -> np.ndarray:
        src = self._buf if src is None else src
        cap = self.capacity
        if hi <= lo:
            return src[:0].copy()
        a, b = lo % cap, hi % cap
        if a < b:
            return src[a:b].copy()
        return np.concatenate((src[a:], src[:b]))
