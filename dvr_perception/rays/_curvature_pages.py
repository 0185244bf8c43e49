"""A whole volume's ``|H|`` kept in 8^3 pages while it is computed, band by band.

:func:`~dvr_perception.rays.curvature.curvature_pages` cuts the volume into y bands whose
edges fall on page edges, so a page belongs to one band.  A band's values go to a
:class:`BandPages`: with one field (the data) the curvature is written in increasing z, so
the band keeps a slab of eight z slices and pages it whenever the next slab begins; with
label fields too (each field writes its own voxels over the whole band) it keeps the band's
slices until the band is done.  Either way no volume-sized array is made.  :func:`assemble`
then numbers the pages in the order :meth:`CurvaturePages.from_dense
<dvr_perception.rays.curvature_field.CurvaturePages.from_dense>` does (C order of the page
grid) and gathers them, freeing each band's pages as they are copied.  The values, the pages
kept and their numbers equal ``from_dense`` of the dense result bit for bit.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PAGE", "BandPages", "assemble", "page_cuts"]

#: Side of a page (a power of two: the walk reads ``z >> 3``, ``z & 7``).
PAGE = 8


def page_cuts(start: int, stop: int, bands: int) -> list[int]:
    """Return at most ``bands`` + 1 cuts of ``[start, stop)`` on multiples of :data:`PAGE`.

    ``start`` is a multiple of :data:`PAGE`; the last cut is ``stop``.

    Examples
    --------
    >>> page_cuts(0, 50, 3)
    [0, 16, 32, 50]
    >>> page_cuts(0, 20, 5)
    [0, 8, 16, 20]
    """
    npage = -(-(stop - start) // PAGE)
    bands = max(1, min(bands, npage))
    cuts = [start + PAGE * ((npage * i) // bands) for i in range(bands)]
    return [*cuts, stop]


class BandPages:
    """The pages of one y band (rows ``y0 ...``, ``y0`` a multiple of 8) of a whole volume.

    Written to as the dense band would be (``band[k]`` is extent slice ``k``'s ``(rows, X)``
    plane, to be written in increasing ``k`` unless ``whole``); :meth:`finish` pages what is
    left.  The pages are kept in one array, ``arena``, as large as the band's page grid but
    filled from its end (memory is only taken where it is written): slab ``q`` (z ``8 q ...``)
    holds ``arena[start:start + count]``, ``slabs[q] = (local, start, count)`` with the
    band's local page numbers ``local`` (``(ceil(rows / 8), ceil(X / 8))``, -1: all zero).
    So the slabs gathered first (:func:`assemble`, in increasing ``q``) lie at the end, and
    the arena shrinks (``realloc``) as they are copied out.

    Parameters
    ----------
    nz, rows, nx : int
        The band's shape.
    y0 : int
        Its first row in the volume.
    nk : module or None
        The curvature kernels (None: numpy).
    whole : bool
        Keep every slice until :meth:`finish` (several fields write the band in turn).
    """

    def __init__(self, nz: int, rows: int, nx: int, y0: int, nk, *, whole: bool) -> None:
        self.nz, self.rows, self.nx, self.y0 = nz, rows, nx, y0
        self.nk = nk
        self.whole = whole
        self.grid = (-(-rows // PAGE), -(-nx // PAGE))
        self.buf = np.zeros((nz if whole else min(PAGE, nz), rows, nx), np.float32)
        self.slab = 0  # the slab held when streaming
        # numba: the pages written with a value that is not 0, per slab held (marked as
        # the values are written: :meth:`mark`); numpy finds them in the slab
        self.flags = np.zeros((len(self.buf) // PAGE + 1, *self.grid), np.uint8)
        self.arena = np.empty((-(-nz // PAGE) * self.grid[0] * self.grid[1], PAGE, PAGE, PAGE),
                              np.float32)  # fmt: skip
        self.top = len(self.arena)  # slabs lie in arena[top:]
        self.slabs: dict[int, tuple[np.ndarray, int, int]] = {}
        self.touched: set[int] = set()

    def __getitem__(self, k: int) -> np.ndarray:
        """Return the plane of extent slice ``k`` to write to."""
        if self.whole:
            return self.buf[k]
        q = k // PAGE
        if q != self.slab:
            self._page(self.buf, q=self.slab)
            self.slab = q
        return self.buf[k - PAGE * q]

    def mark(self, k: int, ys: np.ndarray, xs: np.ndarray) -> None:
        """Note the points ``(ys, xs)`` (band rows, columns) just written to plane ``k``."""
        q = k // PAGE
        i = q if self.whole else 0
        self.nk.mark_pages(self.buf[k if self.whole else k - PAGE * q], ys, xs, self.flags[i])

    def finish(self) -> None:
        """Page what is still held and free the band's planes."""
        if self.whole:
            for q in range(-(-self.nz // PAGE)):
                self._page(self.buf[PAGE * q : PAGE * (q + 1)], q=q)
        else:
            self._page(self.buf, q=self.slab)
        self.buf = None

    def pages(self, q: int) -> np.ndarray:
        """Return the pages of slab ``q`` (a view of the arena)."""
        _, start, count = self.slabs[q]
        return self.arena[start : start + count]

    def _page(self, slab: np.ndarray, *, q: int) -> None:
        """Keep the non-zero pages of ``slab`` (slab ``q``) and zero it."""
        depth = min(PAGE, self.nz - PAGE * q)
        if self.nk is not None:
            flags = self.flags[q if self.whole else 0].view(bool)
            n = int(flags.sum())
            if n == 0:
                return
            index = np.full(self.grid, -1, np.int32)
            index[flags] = np.arange(n, dtype=np.int32)
            flags[...] = False
            self.top -= n
            self.nk.slab_fill(slab, depth, index, self.arena[self.top : self.top + n])
        else:
            py, px = self.grid
            pad = np.zeros((PAGE, py * PAGE, px * PAGE), np.float32)
            pad[:depth, : self.rows, : self.nx] = slab[:depth]
            blocks = pad.reshape(PAGE, py, PAGE, px, PAGE).transpose(1, 3, 0, 2, 4)
            kept = blocks.reshape(py, px, -1).any(axis=2)
            n = int(kept.sum())
            if n == 0:
                return
            index = np.full(self.grid, -1, np.int32)
            index[kept] = np.arange(n, dtype=np.int32)
            self.top -= n
            self.arena[self.top : self.top + n] = blocks[kept]
            slab[:depth] = 0.0
        self.slabs[q] = (index, self.top, n)

    def zero(self, k: np.ndarray | int, ys: np.ndarray, xs: np.ndarray) -> None:
        """Set the voxels ``(k, ys, xs)`` (extent slice, volume row, column) to 0."""
        ks = np.broadcast_to(np.asarray(k, np.int64), np.shape(ys))
        ys = np.asarray(ys, np.int64) - self.y0
        xs = np.asarray(xs, np.int64)
        for q in np.unique(ks // PAGE):
            q = int(q)
            if q not in self.slabs:
                continue  # every value of the slab is 0 already
            index = self.slabs[q][0]
            pages = self.pages(q)
            on = ks // PAGE == q
            kz, ky, kx = ks[on], ys[on], xs[on]
            p = index[ky // PAGE, kx // PAGE]
            there = p >= 0  # a point whose value is 0 may lie on an empty page
            pages[p[there], kz[there] % PAGE, ky[there] % PAGE, kx[there] % PAGE] = 0.0
            self.touched.add(q)

    def drop_zero_pages(self) -> None:
        """Drop the pages that :meth:`zero` left all zero (the others keep their order)."""
        for q in sorted(self.touched):
            if q not in self.slabs:
                continue
            local, start, count = self.slabs[q]
            pages = self.pages(q)
            keep = pages.reshape(count, -1).any(axis=1)
            m = int(keep.sum())
            if m == count:
                continue
            if m == 0:
                del self.slabs[q]
                continue
            renum = np.full(count + 1, -1, np.int32)  # renum[-1] stays -1
            renum[np.flatnonzero(keep)] = np.arange(m, dtype=np.int32)
            pages[:m] = pages[keep]  # a copy first: the order is kept
            self.slabs[q] = (renum[local], start, m)
        self.touched.clear()

    def release(self, q: int) -> None:
        """Forget slab ``q`` and give back the arena from its start on (it was copied out)."""
        held = self.slabs.pop(q, None)
        if held is None:
            return
        keep = held[1]
        if keep == 0:
            self.arena = None
        else:
            # the slabs still held lie below: realloc shrinks the array in place
            self.arena.resize((keep, PAGE, PAGE, PAGE), refcheck=False)


def assemble(bands: list[BandPages], shape) -> tuple[np.ndarray, np.ndarray]:
    """Gather the bands' pages, numbered, into ``(index, pages)`` of a ``shape`` volume.

    Pages in C order of the page grid (slab by slab, the bands in y order within a slab), as
    :meth:`~dvr_perception.rays.curvature_field.CurvaturePages.from_dense` numbers them;
    pages zeroed since they were kept (:meth:`BandPages.zero`) are dropped.  Each band gives
    its memory back as its slabs are copied.
    """
    grid = tuple(-(-n // PAGE) for n in shape)
    index = np.full(grid, -1, np.int32)
    for band in bands:
        band.drop_zero_pages()
    total = sum(c for band in bands for _, _, c in band.slabs.values())
    out = np.empty((total, PAGE, PAGE, PAGE), np.float32)
    n = 0
    for q in range(grid[0]):
        for band in bands:
            if q not in band.slabs:
                continue
            local = band.slabs[q][0]
            count = band.slabs[q][2]
            r0 = band.y0 // PAGE
            part = index[q, r0 : r0 + local.shape[0]]
            there = local >= 0
            part[there] = local[there] + n
            out[n : n + count] = band.pages(q)
            n += count
            band.release(q)
    for band in bands:
        band.arena = None
    return index, out
