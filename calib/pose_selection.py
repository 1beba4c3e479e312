"""Choosing measurement poses: D-optimal or minimum-condition-number subsets of a candidate set.

Paper 003 (section 5) picks positions on the workspace boundary by the condition number of the
identification matrix. Generalised here: given the whitened Jacobian rows of every candidate pose,
``blocks`` (N_candidates, C, n), choose ``k`` poses that

- ``"D"``: maximise ``log det(J^T J)`` (D-optimality: smallest volume of the confidence ellipsoid), or
- ``"condition"``: minimise the condition number of the column-normalised ``J`` (paper 003),

by a greedy start (for ``"condition"``: the D-optimal set, a much better start than greedy) followed by
exchange sweeps (Fedorov): each selected pose is swapped for the best
candidate while that improves the criterion. Vectorised over the candidates via information matrices
``M = sum_i B_i^T B_i``. Units: those of the blocks (whitened residual per parameter unit).
"""

from __future__ import annotations

import numpy as np

CRITERIA = ("D", "condition")


def information(blocks: np.ndarray) -> np.ndarray:
    """Per-pose information matrices ``B_i^T B_i``: (N, n, n)."""
    return np.einsum("kci,kcj->kij", blocks, blocks)


def _score(M: np.ndarray, criterion: str) -> np.ndarray:
    """Criterion to MINIMISE for information matrices (..., n, n)."""
    if criterion == "D":
        sign, logdet = np.linalg.slogdet(M)
        return np.where(sign > 0, -logdet, np.inf)
    d = np.sqrt(np.clip(np.einsum("...ii->...i", M), 1e-300, None))
    lam = np.linalg.eigvalsh(M / (d[..., :, None] * d[..., None, :]))
    return np.where(lam[..., 0] > 0, np.sqrt(lam[..., -1] / np.maximum(lam[..., 0], 1e-300)), np.inf)


def condition_number(blocks: np.ndarray, idx=None) -> float:
    """Condition number of the column-normalised Jacobian of the poses ``idx`` (default all)."""
    I = information(blocks if idx is None else blocks[np.asarray(idx)]).sum(axis=0)
    return float(_score(I, "condition"))


def crlb_std(blocks: np.ndarray, idx=None) -> np.ndarray:
    """Cramér-Rao standard deviation per parameter for the poses ``idx`` (inf if singular)."""
    I = information(blocks if idx is None else blocks[np.asarray(idx)]).sum(axis=0)
    try:
        return np.sqrt(np.clip(np.diag(np.linalg.inv(I)), 0, None))
    except np.linalg.LinAlgError:
        return np.full(I.shape[0], np.inf)


def select_poses(blocks: np.ndarray, k: int, criterion: str = "D", max_sweeps: int = 30,
                 start=None, prior: np.ndarray | None = None) -> np.ndarray:
    """Indices of ``k`` candidate poses chosen by ``criterion`` (see module docstring).

    ``start`` optionally gives the initial subset (default: greedy forward selection). ``prior``
    (n, n), optional: information the fit has besides the poses (its priors, in the blocks' units),
    added to every candidate set (Bayesian D-optimality).
    """
    if criterion not in CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r} (known: {', '.join(CRITERIA)})")
    N, _, n = blocks.shape
    if not 0 < k <= N:
        raise ValueError(f"cannot choose {k} poses out of {N} candidates")
    info = information(blocks)
    ridge = 1e-9 * np.diag(np.einsum("kii->i", info))   # per-parameter (scale-free): defines the first
                                                          # greedy steps, negligible afterwards
    if prior is not None:
        ridge = ridge + prior
    if start is None and criterion == "condition":
        start = select_poses(blocks, k, "D", max_sweeps, prior=prior)   # the greedy condition start is poor
    if start is None:
        chosen: list[int] = []
        M = ridge.copy()
        for _ in range(k):
            s = _score(M + info, criterion)
            s[chosen] = np.inf
            c = int(np.argmin(s))
            chosen.append(c)
            M = M + info[c]
    else:
        chosen = [int(i) for i in start]
    sel = np.array(chosen)
    M = info[sel].sum(axis=0) + ridge
    best = float(_score(M, criterion))
    for _ in range(max_sweeps):
        improved = False
        for pos in range(k):
            trial = M - info[sel[pos]] + info          # swap sel[pos] for every candidate
            s = _score(trial, criterion)
            s[sel] = np.inf
            c = int(np.argmin(s))
            if s[c] < best - 1e-12 * abs(best):
                best, M = float(s[c]), trial[c]
                sel[pos] = c
                improved = True
        if not improved:
            break
    return np.sort(sel)


def join_blocks(*blocks: np.ndarray) -> np.ndarray:
    """Per-pose block-diagonal combination of designs for separate parameter groups (same candidates).

    ``blocks[g]`` is (N, C_g, n_g); the result (N, sum C_g, sum n_g). The D-criterion of the joint
    design is the sum of the groups' log-determinants (scale-free per group), so selecting on it
    balances, e.g., the identification parameters and a regression fitted on the same poses.
    """
    N = blocks[0].shape[0]
    C = sum(b.shape[1] for b in blocks)
    n = sum(b.shape[2] for b in blocks)
    out = np.zeros((N, C, n))
    c = k = 0
    for b in blocks:
        out[:, c:c + b.shape[1], k:k + b.shape[2]] = b
        c, k = c + b.shape[1], k + b.shape[2]
    return out
