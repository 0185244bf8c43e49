"""Curvature for the engine without a dense whole-volume array.

:func:`curvature_source` returns what :func:`~dvr_perception.rays.engine.analyze` takes as
``curvature``: the float32 ``|H|`` volume stored in pages (:class:`CurvaturePages`: ``|H|`` is
0 off the structures' boundaries, so most 8^3 pages hold nothing and are not stored) when the
volume is small enough to analyse whole, else a :class:`CurvatureField` that computes each
brick's piece when a bricked analysis walks it
(:func:`~dvr_perception.rays.curvature.curvature_volume` with ``extent``; the whole-volume
quantities are computed once, so every piece equals the slice of the whole result).
"""

from __future__ import annotations

import numpy as np

from dvr_perception._numba import kernels
from dvr_perception._progress import reporter
from dvr_perception.errors import DVRInputError
from dvr_perception.rays._curvature_pages import PAGE
from dvr_perception.rays.curvature import curvature_globals, curvature_pages, curvature_volume

__all__ = ["PAGE", "CurvatureField", "CurvaturePages", "curvature_source"]


class CurvaturePages:
    """A float32 ``(Z, Y, X)`` volume kept as its non-zero 8^3 pages.

    ``index[z // 8, y // 8, x // 8]`` is the page holding voxel ``(z, y, x)`` in ``pages``
    (``(n, 8, 8, 8)``), or -1 where every value of that page is 0.  The walk reads a voxel
    through the index (:func:`~dvr_perception.rays._numba_kernels._curv_at`); ``np.asarray``
    gives the dense volume back, :meth:`piece` a dense part of it (what a brick reads).
    :meth:`from_volume` computes a volume's ``|H|`` straight into pages (no dense array),
    :meth:`from_dense` pages an array.

    Parameters
    ----------
    index : numpy.ndarray
        int32 ``(ceil(Z / 8), ceil(Y / 8), ceil(X / 8))`` page numbers, -1 for an empty page.
    pages : numpy.ndarray
        float32 ``(n, 8, 8, 8)``; voxels of an edge page outside the volume are 0.
    shape : tuple of int
        ``(Z, Y, X)``.

    Examples
    --------
    >>> dense = np.zeros((10, 20, 17), np.float32)
    >>> dense[9, 3, 16] = 2.5
    >>> paged = CurvaturePages.from_dense(dense)
    >>> paged.index.shape, paged.pages.shape
    ((2, 3, 3), (1, 8, 8, 8))
    >>> bool(np.array_equal(np.asarray(paged), dense))
    True
    >>> float(paged.piece(((9, 10), (3, 4), (16, 17)))[0, 0, 0])
    2.5
    """

    def __init__(self, index: np.ndarray, pages: np.ndarray, shape) -> None:
        self.index = np.ascontiguousarray(index, np.int32)
        self.pages = np.ascontiguousarray(pages, np.float32)
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(np.float32)
        # the walk reads through the index unchecked: every page number must exist
        grid = tuple(-(-n // PAGE) for n in self.shape)
        if self.index.shape != grid or self.pages.shape[1:] != (PAGE, PAGE, PAGE):
            raise DVRInputError(
                f"curvature: pages of a {self.shape} volume need an index of shape {grid} "
                f"and pages of shape (n, {PAGE}, {PAGE}, {PAGE}), got {self.index.shape} "
                f"and {self.pages.shape}"
            )
        if self.index.size and not -1 <= int(self.index.min()) <= int(self.index.max()) < len(
            self.pages
        ):
            raise DVRInputError(
                f"curvature: page numbers must be -1 (empty) or below {len(self.pages)}"
            )

    @property
    def nbytes(self) -> int:
        """Bytes held (index and pages)."""
        return int(self.index.nbytes + self.pages.nbytes)

    @classmethod
    def from_dense(cls, dense: np.ndarray) -> CurvaturePages:
        """Page ``dense`` (float32 ``(Z, Y, X)``)."""
        dense = np.ascontiguousarray(dense, np.float32)
        nk = kernels("dvr_perception.rays._numba_grid")
        if nk is None:
            return cls(*_paged(dense), dense.shape)
        flags = np.zeros([-(-n // PAGE) for n in dense.shape], np.uint8)
        nk.page_flags(dense, flags)
        kept = flags.reshape(-1).view(bool)
        index = np.full(flags.shape, -1, np.int32)
        index.reshape(-1)[kept] = np.arange(int(kept.sum()), dtype=np.int32)
        pages = np.zeros((int(kept.sum()), PAGE, PAGE, PAGE), np.float32)
        nk.page_fill(dense, index, pages)
        return cls(index, pages, dense.shape)

    @classmethod
    def from_volume(cls, volume, spec, *, sigma: float = 1.0, gradient_max=None,
                    progress=None) -> CurvaturePages:  # fmt: skip
        """Page ``volume``'s ``|H|`` as it is computed, never holding it dense.

        :func:`~dvr_perception.rays.curvature.curvature_pages`: equal to
        ``from_dense(curvature_volume(volume, spec, ...)[0])``, pages and their numbers
        included.
        """
        index, pages = curvature_pages(
            volume, spec, sigma=sigma, gradient_max=gradient_max, progress=progress
        )
        return cls(index, pages, volume.data.shape)

    def kernel_arg(self) -> tuple:
        """``(index, pages)``: what the numba walk reads."""
        return self.index, self.pages

    def piece(self, extent) -> np.ndarray:
        """Dense float32 values on the voxels ``extent = ((z0, z1), (y0, y1), (x0, x1))``."""
        (z0, z1), (y0, y1), (x0, x1) = ((int(a), int(b)) for a, b in extent)
        out = np.zeros((z1 - z0, y1 - y0, x1 - x0), np.float32)
        if self.pages.shape[0] == 0 or out.size == 0:
            return out
        nk = kernels("dvr_perception.rays._numba_grid")
        if nk is not None:
            nk.page_read(self.index, self.pages, z0, y0, x0, out)
            return out
        lo = [a // PAGE for a in (z0, y0, x0)]
        hi = [-(-b // PAGE) for b in (z1, y1, x1)]
        sub = self.index[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        stored = np.zeros((*sub.shape, PAGE, PAGE, PAGE), np.float32)
        there = sub >= 0
        stored[there] = self.pages[sub[there]]
        block = stored.transpose(0, 3, 1, 4, 2, 5).reshape([s * PAGE for s in sub.shape])
        oz, oy, ox = (a - q * PAGE for a, q in zip((z0, y0, x0), lo, strict=True))
        out[...] = block[oz : oz + out.shape[0], oy : oy + out.shape[1], ox : ox + out.shape[2]]
        return out

    def __array__(self, dtype=None, copy=None):
        """Return the dense volume."""
        out = self.piece(tuple((0, n) for n in self.shape))
        return out if dtype is None else out.astype(dtype)


class CurvatureField:
    """``|H|`` of ``volume``'s structure boundaries, computed piece by piece on demand.

    Parameters
    ----------
    volume, spec, sigma
        As :func:`~dvr_perception.rays.curvature.curvature_volume`.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> field = CurvatureField(vol, spec)
    >>> whole = curvature_volume(vol, spec)[0]
    >>> piece = field.piece(((3, 9), (0, 24), (5, 20)))
    >>> bool(np.array_equal(piece, whole[3:9, :, 5:20]))
    True
    """

    def __init__(self, volume, spec, *, sigma: float = 1.0) -> None:
        self.volume = volume
        self.spec = spec
        self.sigma = float(sigma)
        self.shape = volume.data.shape
        self._globals = None

    @property
    def globals(self):
        """The whole-volume quantities (computed once)."""
        if self._globals is None:
            self._globals = curvature_globals(self.volume, self.spec, sigma=self.sigma)
        return self._globals

    def piece(self, extent) -> np.ndarray:
        """float32 ``|H|`` on the voxels ``extent = ((z0, z1), (y0, y1), (x0, x1))``."""
        extent = tuple((int(a), int(b)) for a, b in extent)
        out, _ = curvature_volume(
            self.volume, self.spec, sigma=self.sigma, extent=extent, gradient_max=self.globals
        )
        return np.ascontiguousarray(out, np.float32)

    def __array__(self, dtype=None, copy=None):
        """Return the whole volume's ``|H|`` (what a whole-volume analysis reads)."""
        out, _ = curvature_volume(
            self.volume, self.spec, sigma=self.sigma, gradient_max=self.globals
        )
        return out if dtype is None else out.astype(dtype)


def _paged(dense: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(index, pages)`` of ``dense`` without numba, one slab of 8 planes at a time."""
    ny, nx = dense.shape[1:]
    pz, py, px = (-(-n // PAGE) for n in dense.shape)
    index = np.full((pz, py, px), -1, np.int32)
    slab = np.zeros((PAGE, py * PAGE, px * PAGE), np.float32)
    kept, n = [], 0
    for z in range(pz):
        part = dense[z * PAGE : (z + 1) * PAGE]
        slab[...] = 0.0
        slab[: part.shape[0], :ny, :nx] = part
        blocks = slab.reshape(PAGE, py, PAGE, px, PAGE).transpose(1, 3, 0, 2, 4)
        full = blocks.reshape(py, px, -1).any(axis=2)
        m = int(full.sum())
        if m:
            index[z][full] = np.arange(n, n + m, dtype=np.int32)
            kept.append(blocks[full])  # (m, 8, 8, 8), a copy
            n += m
    pages = np.concatenate(kept) if kept else np.zeros((0, PAGE, PAGE, PAGE), np.float32)
    return index, pages


def curvature_source(volume, spec, *, sigma: float = 1.0, memory_limit=None, progress=None):
    """Return the ``curvature`` to give :func:`~dvr_perception.rays.engine.analyze`.

    The float32 volume, in pages (:class:`CurvaturePages`, paged as it is computed:
    :meth:`CurvaturePages.from_volume`), when the volume, its derived
    volumes and a dense float32 array fit the memory
    limit (:func:`~dvr_perception.rays.memory.whole_fits`: the whole-volume analysis's share
    of :func:`~dvr_perception.rays.memory.plan`, however many voxels), else a
    :class:`CurvatureField`.  ``progress``: as
    :func:`~dvr_perception.rays.curvature.curvature_volume`'s (a field reports 0.0 and 1.0
    at once: its pieces are computed, and reported, by the bricked analysis that walks them).
    """
    from dvr_perception.rays import memory

    report = reporter(progress)
    if memory.whole_fits(volume, memory_limit):
        return CurvaturePages.from_volume(volume, spec, sigma=sigma, progress=report)
    report(0.0)
    report(1.0)
    return CurvatureField(volume, spec, sigma=sigma)
