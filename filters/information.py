"""Sparse information-matrix algebra: a Gaussian in information form ``(eta, Lambda)`` over a
growing list of entities (:class:`SparseInformation`, CM (4)-(5): constant-time block edits, a
global solve only when needed) and the sparse factorisation of a symmetric positive definite
matrix (:func:`sparse_spd_factor`).

The delayed-state filters (:mod:`filters.esdf`, :mod:`filters.relative_esdf`), the relative
back-end (:mod:`filters.back_ends`) and the optimisers (:mod:`filters.optimiser`,
:mod:`filters.submap_optimise`, :mod:`filters.submap_gauss_newton`) share it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse.linalg import splu

from filters.validation import require


def symmetrise(a):
    """``(a + a^T) / 2``."""
    return 0.5 * (a + a.T)


class SparseInformation:
    """A Gaussian in information form ``(eta, Lambda)`` over a growing list of entities.

    Each entity is a block of ``size`` consecutive coordinates (a pose: 3, a point: 2, ...).
    ``Lambda`` is stored as a dict of dense blocks keyed ``(i, j)`` with ``i <= j`` (the lower
    triangle is the transpose, so the assembled matrix is exactly symmetric), with a neighbour set
    per entity; ``eta`` as one small vector per entity. :meth:`add_information` (CM (4)-(5)) and
    :meth:`add_entity` touch only the blocks they must, in time independent of the state size.
    :meth:`matrix` assembles ``scipy.sparse`` CSC; :meth:`mean`, :meth:`marginals` and
    :meth:`covariance_blocks` solve with a sparse LU factorisation cached until the next edit.
    """

    def __init__(self):
        self._sizes: list[int] = []
        self._offsets: list[int] = []
        self.dim = 0
        self._eta: list[np.ndarray] = []
        self._blocks: dict[tuple[int, int], np.ndarray] = {}
        self._nbrs: list[set[int]] = []
        self.version = 0
        self._cache: dict[str, tuple[int, object]] = {}

    def __getstate__(self):
        # the cache holds a SuperLU factor, which does not pickle; it is rebuilt on demand
        state = self.__dict__.copy()
        state["_cache"] = {}
        return state

    # ----------------------------------------------------------------- structure
    @property
    def n_entities(self) -> int:
        return len(self._sizes)

    def size(self, e: int) -> int:
        return self._sizes[e]

    def offset(self, e: int) -> int:
        return self._offsets[e]

    def neighbours(self, e: int) -> set[int]:
        """Entities sharing a non-zero off-diagonal block with ``e``."""
        return self._nbrs[e]

    def add_entity(self, size: int) -> int:
        """Append an entity with no information (zero blocks); returns its index."""
        e = len(self._sizes)
        self._sizes.append(int(size))
        self._offsets.append(self.dim)
        self.dim += int(size)
        self._eta.append(np.zeros(size))
        self._blocks[(e, e)] = np.zeros((size, size))
        self._nbrs.append(set())
        self.version += 1
        return e

    def block(self, i: int, j: int):
        """The ``(i, j)`` block of ``Lambda`` (a view for ``i <= j``), or ``None`` if zero."""
        if i <= j:
            return self._blocks.get((i, j))
        b = self._blocks.get((j, i))
        return None if b is None else b.T

    def eta_of(self, e: int) -> np.ndarray:
        return self._eta[e]

    def add_information(self, entities, H_blocks, W, rhs) -> None:
        """``Lambda += H^T W H`` and ``eta += H^T W rhs`` for ``H = [H_1 ... H_q]`` (CM (4)-(5)).

        For a measurement ``z = h(x) + v``, ``v ~ N(0, W^-1)``, linearised at ``mu_bar``, pass
        ``rhs = z - h(mu_bar) + H mu_bar`` (CM (5)). ``entities`` must be distinct. Touches the
        ``q (q + 1) / 2`` blocks among the listed entities only.
        """
        entities = [int(e) for e in entities]
        require(len(set(entities)) == len(entities), "entities", entities, "distinct entities")
        W = np.asarray(W, dtype=float)
        rhs = np.asarray(rhs, dtype=float)
        WH = [W @ H for H in H_blocks]
        Wr = W @ rhs
        for a, (ea, Ha) in enumerate(zip(entities, H_blocks, strict=True)):
            self._eta[ea] = self._eta[ea] + Ha.T @ Wr
            self._blocks[(ea, ea)] += symmetrise(Ha.T @ WH[a])
            for b in range(a + 1, len(entities)):
                eb = entities[b]
                blk = Ha.T @ WH[b]
                key, val = ((ea, eb), blk) if ea < eb else ((eb, ea), blk.T)
                old = self._blocks.get(key)
                if old is None:
                    self._blocks[key] = val.copy()
                    self._nbrs[ea].add(eb)
                    self._nbrs[eb].add(ea)
                else:
                    old += val
        self.version += 1

    # ----------------------------------------------------------------- global forms
    def vector(self) -> np.ndarray:
        """``eta`` as one dense vector."""
        return np.concatenate(self._eta) if self._eta else np.zeros(0)

    def matrix(self) -> sp.csc_matrix:
        """``Lambda`` as a symmetric ``scipy.sparse`` CSC matrix (cached until the next edit)."""
        hit = self._cache.get("matrix")
        if hit is not None and hit[0] == self.version:
            return hit[1]
        rows, cols, vals = [], [], []
        off = self._offsets
        for (i, j), b in self._blocks.items():
            si, sj = b.shape
            r = np.repeat(np.arange(off[i], off[i] + si), sj)
            c = np.tile(np.arange(off[j], off[j] + sj), si)
            v = b.ravel()
            rows.append(r)
            cols.append(c)
            vals.append(v)
            if i != j:
                rows.append(c)
                cols.append(r)
                vals.append(v)
        if rows:
            m = sp.coo_matrix(
                (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                shape=(self.dim, self.dim),
            ).tocsc()
        else:
            m = sp.csc_matrix((0, 0))
        self._cache["matrix"] = (self.version, m)
        return m

    def factor(self):
        """Sparse LU factorisation of ``Lambda`` (``scipy.sparse.linalg.splu``), cached."""
        hit = self._cache.get("factor")
        if hit is not None and hit[0] == self.version:
            return hit[1]
        f = sparse_spd_factor(self.matrix())
        self._cache["factor"] = (self.version, f)
        return f

    def mean(self) -> np.ndarray:
        """The exact mean ``Lambda^-1 eta`` by one sparse solve (cached until the next edit)."""
        hit = self._cache.get("mean")
        if hit is not None and hit[0] == self.version:
            return hit[1]
        mu = self.factor().solve(self.vector())
        self._cache["mean"] = (self.version, mu)
        return mu

    def mean_of(self, e: int, mu: np.ndarray | None = None) -> np.ndarray:
        mu = self.mean() if mu is None else mu
        o = self._offsets[e]
        return mu[o : o + self._sizes[e]]

    def covariance_blocks(self, functionals, chunk_columns: int = 512) -> list[np.ndarray]:
        """Covariances ``J_i Lambda^-1 J_i^T`` of linear functionals of the state.

        Each functional is a list of ``(entity, J_block)`` pairs, ``J_block`` of shape
        ``(d_i, size(entity))``. Multi-column solves ``Lambda X = J^T`` with the cached
        factorisation, ``chunk_columns`` right-hand sides at a time (bounded memory); no inverse
        of ``Lambda`` is formed.
        """
        out: list[np.ndarray] = []
        start = 0
        while start < len(functionals):
            chunk, cols = [], 0
            while start < len(functionals) and (not chunk or cols < chunk_columns):
                f = functionals[start]
                chunk.append(f)
                cols += f[0][1].shape[0]
                start += 1
            out.extend(self._covariance_chunk(chunk))
        return out

    def _covariance_chunk(self, functionals) -> list[np.ndarray]:
        dims = [f[0][1].shape[0] for f in functionals]
        starts = np.concatenate([[0], np.cumsum(dims)]).astype(int)
        B = np.zeros((self.dim, int(starts[-1])))
        for f, c0, d in zip(functionals, starts[:-1], dims, strict=True):
            for e, J in f:
                o = self._offsets[e]
                B[o : o + self._sizes[e], c0 : c0 + d] += J.T
        X = self.factor().solve(B)
        out = []
        for f, c0, d in zip(functionals, starts[:-1], dims, strict=True):
            C = np.zeros((d, d))
            for e, J in f:
                o = self._offsets[e]
                C += J @ X[o : o + self._sizes[e], c0 : c0 + d]
            out.append(symmetrise(C))
        return out

    def marginals(self, entities) -> list[np.ndarray]:
        """Marginal covariance blocks of the listed entities (columns of ``Lambda^-1`` only)."""
        return self.covariance_blocks([[(e, np.eye(self._sizes[e]))] for e in entities])

    # ----------------------------------------------------------------- partial recovery
    def solve_window(self, active, means: list[np.ndarray]) -> dict[int, np.ndarray]:
        """Block Gauss-Seidel step on ``active``: solve ``Lambda_AA mu_A = eta_A - Lambda_AB mu_B``.

        ``means`` holds every entity's current mean; entities outside ``active`` are held fixed.
        Reads only the active blocks and their neighbours' blocks (constant time when the active
        set and the entities' degrees are bounded). Returns ``{entity: new mean}``.
        """
        active = list(dict.fromkeys(int(e) for e in active))
        pos: dict[int, int] = {}
        n = 0
        for e in active:
            pos[e] = n
            n += self._sizes[e]
        A = np.zeros((n, n))
        b = np.zeros(n)
        for e in active:
            i0, se = pos[e], self._sizes[e]
            b[i0 : i0 + se] = self._eta[e]
            A[i0 : i0 + se, i0 : i0 + se] = self._blocks[(e, e)]
            for nb in self._nbrs[e]:
                blk = self.block(e, nb)
                j0 = pos.get(nb)
                if j0 is None:
                    b[i0 : i0 + se] -= blk @ means[nb]
                else:
                    A[i0 : i0 + se, j0 : j0 + self._sizes[nb]] = blk
        x = cho_solve(cho_factor(A), b)
        return {e: x[pos[e] : pos[e] + self._sizes[e]].copy() for e in active}


class _SpdFactor:
    """A sparse LU of a symmetric positive definite matrix with a ``solve`` method."""

    def __init__(self, lu, n):
        self._lu = lu
        self.n = n

    def solve(self, b):
        b = np.asarray(b, dtype=float)
        if self.n == 0:
            return np.zeros_like(b)
        return self._lu.solve(b)


def sparse_spd_factor(A) -> _SpdFactor:
    """``splu`` of a sparse symmetric positive definite matrix (symmetric ordering, no pivoting)."""
    A = sp.csc_matrix(A)
    if A.shape[0] == 0:
        return _SpdFactor(None, 0)
    lu = splu(
        A,
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    return _SpdFactor(lu, A.shape[0])
