"""lightrig for Python: sessions, fits, imaging and the virtual rig as NumPy arrays.

A thin layer over lightrig's Rust crates (the same readers and fits the ``lightrig`` command
runs). See docs/python.md.

    import lightrig
    run = lightrig.demo("lls", quick=True)
    s = lightrig.Session(run["sessions"][0])
    for f in s.frames(step=s.steps()[0]["id"]):
        print(f.frame, f.trigger["snapshot"]["axes"], f.pixels.mean())
"""

from __future__ import annotations

import os
from typing import Any, Callable, Optional, Sequence, Union

from . import _lightrig
from ._lightrig import (  # noqa: F401  (re-exported)
    DemoError,
    FitError,
    Frame,
    FrameIter,
    ImageError,
    LightrigError,
    Session,
    SessionError,
    calibrate,
    hdr_merge,
    hdr_response,
    read_image,
    read_spectral_exr,
    write_spectral_exr,
)

__version__ = _lightrig.__version__

Progress = Union[bool, None, Callable[[int, int], Any]]
PathLike = Union[str, "os.PathLike[str]"]


def _progress(progress: Progress, desc: str) -> Optional[Callable[[int, int], Any]]:
    """A ``(done, total)`` callback: the caller's, a tqdm bar (if tqdm is installed) or none."""
    if progress is None or progress is False:
        return None
    if callable(progress):
        return progress
    try:
        from tqdm.auto import tqdm  # type: ignore[import-untyped]
    except ImportError:  # no tqdm: a line on stderr every tenth
        import sys

        shown = [-1]

        def line(done: int, total: int) -> None:
            tenth = (10 * done) // total if total else 0
            if tenth != shown[0]:
                shown[0] = tenth
                print(f"{desc}: {done}/{total}", file=sys.stderr)

        return line
    bar = tqdm(desc=desc, total=0)

    def update(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
            bar.refresh()
        bar.update(done - bar.n)
        if total and done >= total:
            bar.close()

    return update


def write_image(path: PathLike, pixels: Any, precision: str = "half", bits: int = 16) -> None:
    """Writes ``pixels`` ((height, width[, channels]), any real dtype, taken as float32) to
    ``path``: ``.exr`` (``precision`` "half" or "float"), ``.png`` or ``.tif`` (``bits`` 8 or 16,
    values in [0, 1])."""
    import numpy as np

    _lightrig.write_image(path, np.ascontiguousarray(pixels, dtype=np.float32), precision, bits)


def _set(set: Optional[Sequence[str]]) -> Optional[list[str]]:
    """``set=`` as the extension takes it: a list of ``"KEY=VALUE"`` strings (one string alone
    is refused, not split into characters)."""
    if set is None:
        return None
    if isinstance(set, (str, bytes)):
        raise LightrigError(f"set={set!r}: give a list of KEY=VALUE strings, e.g. set=[{set!r}]")
    return [str(s) for s in set]


def fit_lls(session: PathLike, calibration: Optional[PathLike] = None, out: Optional[PathLike] = None,
            progress: Progress = False, set: Optional[Sequence[str]] = None) -> dict:
    """``lightrig fit lls``: per-pixel diffuse, specular, roughness, points, normals, translucency.
    ``set``: the session's rig file changed as ``lightrig fit --set`` does, ``["KEY=VALUE", …]``."""
    return _lightrig.fit_lls(session, calibration, out, _progress(progress, "lls"), _set(set))


def fit_firs_surface(session: PathLike, out: Optional[PathLike] = None, progress: Progress = False,
                     set: Optional[Sequence[str]] = None) -> dict:
    """``lightrig fit firs-surface``: the surface points of each orientation, and merged."""
    return _lightrig.fit_firs_surface(session, out, _progress(progress, "firs-surface"), _set(set))


def fit_firs_volume(session: PathLike, out: Optional[PathLike] = None, progress: Progress = False,
                    set: Optional[Sequence[str]] = None) -> dict:
    """``lightrig fit firs-volume``: the occupancy volume (z, y, x) and its isosurface."""
    return _lightrig.fit_firs_volume(session, out, _progress(progress, "firs-volume"), _set(set))


def fit_display(session: PathLike, calibration: Optional[PathLike] = None, out: Optional[PathLike] = None,
                set: Optional[Sequence[str]] = None) -> dict:
    """``lightrig fit display``: a display calibration, or what a display session showed."""
    return _lightrig.fit_display(session, calibration, out, _set(set))


def fit_brrdf(session: PathLike, spectralon: Optional[PathLike] = None, out: Optional[PathLike] = None,
              progress: Progress = False, set: Optional[Sequence[str]] = None) -> dict:
    """``lightrig fit brrdf``: wavelength pairs, per-sphere samples and bins, the PCA figures."""
    return _lightrig.fit_brrdf(session, spectralon, out, _progress(progress, "brrdf"), _set(set))


def fit_disco(session: PathLike, mesh: Optional[PathLike] = None, out: Optional[PathLike] = None,
              progress: Progress = False, set: Optional[Sequence[str]] = None) -> dict:
    """``lightrig fit disco``: the throughput factor matrix F on the mesh, and the fit's figures."""
    return _lightrig.fit_disco(session, mesh, out, _progress(progress, "disco"), _set(set))


_FITS: dict[str, Callable[..., dict]] = {
    "lls": fit_lls,
    "firs-surface": fit_firs_surface,
    "firs-volume": fit_firs_volume,
    "display": fit_display,
    "brdf-display": fit_display,
    "brrdf": fit_brrdf,
    "bispectral": fit_brrdf,
    "disco": fit_disco,
}


def fit(pipeline: str, session: PathLike, **options: Any) -> dict:
    """``lightrig fit PIPELINE SESSION``: ``options`` are the command's (``calibration``,
    ``spectralon``, ``mesh``, ``out``, ``set``) and ``progress``."""
    try:
        f = _FITS[pipeline]
    except KeyError:
        raise LightrigError(
            f"lightrig.fit({pipeline!r}): the pipelines are: lls, firs-surface, firs-volume, display, brrdf, disco"
        ) from None
    return f(session, **options)


def demo(method: str = "lls", quick: bool = True, out: PathLike = "lightrig-demo", seed: int = 1,
         check: bool = False, progress: bool = False) -> dict:
    """``lightrig demo METHOD``: acquire and fit on the virtual rig, report against its truth."""
    return _lightrig.demo(method, quick, out, seed, check, progress)


def open_session(path: PathLike) -> Session:
    """A session directory, read-only (``Session(path)``)."""
    return Session(path)
