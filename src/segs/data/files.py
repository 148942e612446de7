"""Reading dataset files: checked paths, text index/table files and images.

Every problem with the user's files raises :class:`segs.errors.DataError` with a one-line message
naming the file (and the line for text files) and what was expected.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from segs.errors import DataError


def require_dir(path: str | Path, what: str = "dataset folder") -> Path:
    """The folder as a Path, or DataError when it does not exist."""
    path = Path(path).expanduser()
    if not path.is_dir():
        raise DataError(f"{path}: {what} not found")
    return path


def require_file(path: str | Path, what: str = "file") -> Path:
    """The file as a Path, or DataError when it does not exist."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} not found")
    return path


def _show(token: str) -> str:
    """A token quoted safely for a one-line message."""
    return repr(token if len(token) <= 40 else token[:37] + "...")


def read_rows(path: Path, columns: tuple[int, int], sep: str | None = None) -> list[tuple[int, list[str]]]:
    """Non-empty, non-comment ('#') lines of a text table split on `sep` (None = whitespace).

    columns: (min, max) number of fields accepted. Returns [(line_number, fields)].
    """
    path = require_file(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read text file ({type(exc).__name__})") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(sep)]
        if not columns[0] <= len(fields) <= columns[1]:
            want = columns[0] if columns[0] == columns[1] else f"{columns[0]} to {columns[1]}"
            raise DataError(f"{path}:{lineno}: expected {want} columns, got {len(fields)}")
        rows.append((lineno, fields))
    return rows


def to_float(token: str, path: Path, lineno: int, what: str = "number") -> float:
    """A finite float, or DataError naming file and line."""
    try:
        value = float(token)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value):
        raise DataError(f"{path}:{lineno}: expected a finite {what}, got {_show(token)}")
    return value


def to_int(token: str, path: Path, lineno: int, what: str = "integer") -> int:
    """A non-negative integer (e.g. nanoseconds), or DataError naming file and line."""
    if not token.isdigit() or not token.isascii():
        raise DataError(f"{path}:{lineno}: expected a non-negative {what}, got {_show(token)}")
    if int(token) > np.iinfo(np.int64).max:
        raise DataError(f"{path}:{lineno}: {what} {_show(token)} is out of range (>= 2^63)")
    return int(token)


def check_increasing(times: np.ndarray, path: Path, linenos: list[int]) -> None:
    """DataError at the first timestamp that is not strictly greater than the previous one."""
    bad = np.flatnonzero(np.diff(times) <= 0)
    if len(bad):
        i = bad[0] + 1
        kind = "duplicate" if times[i] == times[i - 1] else "decreasing"
        raise DataError(f"{path}:{linenos[i]}: {kind} timestamp (timestamps must increase)")


def read_numeric(path: Path, columns: tuple[int, int],
                 sep: str | None = None) -> tuple[np.ndarray, list[int]]:
    """A table of finite numbers: ([N, columns[0]] float64, line numbers); extra columns ignored."""
    rows = read_rows(path, columns, sep)
    data = np.array([[to_float(tok, path, n) for tok in f[: columns[0]]] for n, f in rows])
    return data.reshape(len(rows), columns[0]), [n for n, _ in rows]


def read_timestamped_paths(path: Path, sep: str | None = None) -> tuple[np.ndarray, list[str], list[int]]:
    """TUM-style index 'timestamp filename' -> (times [N] float64 s, names, line numbers).

    Timestamps must be finite and strictly increasing.
    """
    rows = read_rows(path, (2, 2), sep)
    times = np.array([to_float(f[0], path, n, "timestamp") for n, f in rows], np.float64)
    linenos = [n for n, _ in rows]
    check_increasing(times, path, linenos)
    return times, [f[1] for _, f in rows], linenos


def check_files_exist(folder: Path, names: list[str], index: Path, linenos: list[int]) -> list[Path]:
    """Paths folder/name for every name; DataError naming the index line of the first missing one."""
    paths = [folder / name for name in names]
    for p, n in zip(paths, linenos):
        if not p.is_file():
            raise DataError(f"{index}:{n}: lists {p}, which does not exist")
    return paths


def jpeg_is_complete(data: bytes) -> bool:
    """Whether a JPEG byte stream reaches its end-of-image marker (FFD9) through its segments.

    libjpeg decodes a truncated file as far as the data goes, fills the rest with grey and only
    warns on stderr, so OpenCV returns a half-grey image as if nothing were wrong. This walks the
    marker segments (lengths skipped, so EXIF thumbnails do not count) and the entropy-coded data
    of each scan (where FF is followed by 00 or a restart marker); data after FFD9 is ignored.
    """
    n, pos = len(data), 2
    while pos < n:
        pos = data.find(b"\xff", pos)  # garbage between segments is skipped, as libjpeg does
        if pos < 0:
            return False
        while pos < n and data[pos] == 0xFF:  # fill bytes
            pos += 1
        if pos >= n:
            return False
        marker, pos = data[pos], pos + 1
        if marker == 0xD9:
            return True
        if 0xD0 <= marker <= 0xD7 or marker in (0x00, 0x01):  # no length field
            continue
        if pos + 2 > n:
            return False
        pos += int.from_bytes(data[pos : pos + 2], "big")
        if marker == 0xDA:  # start of scan: entropy-coded data up to the next real marker
            while (pos := data.find(b"\xff", pos)) >= 0 and pos + 1 < n and (data[pos + 1] == 0 or 0xD0 <= data[pos + 1] <= 0xD7):
                pos += 2
            if pos < 0 or pos + 1 >= n:
                return False
    return False


def _imread(path: Path) -> np.ndarray:
    """Decode an image file as stored (OpenCV); DataError naming the file when it is missing,
    unreadable, corrupt or a truncated JPEG (which OpenCV would return half grey)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        data = b""
    if data[:2] == b"\xff\xd8" and not jpeg_is_complete(data):
        raise DataError(f"{path}: truncated JPEG (the data ends before the end-of-image marker)")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    except cv2.error:
        img = None
    if img is None:
        raise DataError(f"{path}: cannot read image (missing, unreadable or corrupt)")
    return img


def read_rgb(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Colour or grey 8/16-bit image -> [H,W,3] float32 RGB in [0,1] (grey replicated).

    shape: expected (H, W), checked when given.
    """
    img = _imread(path)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype)
    if scale is None:
        raise DataError(f"{path}: expected an 8- or 16-bit image, got {img.dtype}")
    channels = 1 if img.ndim == 2 else img.shape[2]
    if channels not in (1, 3, 4):
        raise DataError(f"{path}: expected a grey or colour image, got {channels} channels")
    if shape is not None and img.shape[:2] != tuple(shape):
        raise DataError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected {shape[1]}x{shape[0]}")
    if channels == 1:
        img = np.divide(img, np.float32(scale), dtype=np.float32)
        return np.repeat(img.reshape(img.shape[0], img.shape[1], 1), 3, axis=2)
    # BGR(A) -> RGB on the integers, then one division pass (20x faster than a float copy, a
    # division and a reversed copy; the same float32 values)
    rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if channels == 3 else cv2.COLOR_BGRA2RGB)
    return np.divide(rgb, np.float32(scale), dtype=np.float32)


def read_depth(path: Path, scale: float, shape: tuple[int, int] | None = None) -> np.ndarray:
    """16-bit single-channel depth image -> [H,W] float32 metres (value / scale, 0 = invalid).

    shape: expected (H, W) (the colour image's), checked when given.
    """
    img = _imread(path)
    if img.dtype != np.uint16 or img.ndim != 2:
        channels = 1 if img.ndim == 2 else img.shape[2]
        raise DataError(f"{path}: expected a 16-bit single-channel depth image, "
                        f"got {img.dtype} with {channels} channels")
    if shape is not None and img.shape != tuple(shape):
        raise DataError(f"{path}: depth image is {img.shape[1]}x{img.shape[0]}, "
                        f"expected {shape[1]}x{shape[0]} like the colour image")
    return img.astype(np.float32) / np.float32(scale)


def image_shape(path: Path) -> tuple[int, int]:
    """(H, W) of an image file (reads it)."""
    return _imread(path).shape[:2]
