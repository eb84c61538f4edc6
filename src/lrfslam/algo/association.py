"""Data association for point landmarks: gated nearest neighbour and JCBB.

Both functions work on quantities the filter has already computed against the
prior state, so this module knows nothing about the state layout:

* individual innovations ``nu[k, l]`` (observation ``k`` against landmark ``l``)
  and their 2×2 covariances ``S[k, l]``;
* for JCBB, the joint covariance of all individually compatible candidate
  pairings, which carries the pose–landmark and landmark–landmark correlations
  that make a *set* of pairings jointly (in)compatible.

A pairing array has shape (K,) and holds, for each observation, the index of its
landmark (0..L-1) or ``-1`` for "not paired".

References
----------
T. Bailey, ``data_associate.m`` in the ekfslam_v2 simulator (2004): gated nearest
neighbour on ``NIS + ln|S|``.
J. Neira and J. D. Tardós, "Data association in stochastic mapping using the
joint compatibility test", IEEE T-RA 17(6):890–897, 2001.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

UNPAIRED = -1


def nis_2d(innovations: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised innovation squared and ``ln|S|`` for batches of 2-D innovations.

    Parameters
    ----------
    innovations : ndarray, shape (..., 2)
        Innovations ``nu`` (any units, consistent with ``covs``; angles wrapped).
    covs : ndarray, shape (..., 2, 2)
        Innovation covariances ``S``, symmetric positive definite.

    Returns
    -------
    nis : ndarray, shape (...)
        ``nu^T S^-1 nu`` (dimensionless, χ²₂-distributed if the filter is consistent).
    log_det : ndarray, shape (...)
        ``ln|S|``.
    """
    a, b, d = covs[..., 0, 0], covs[..., 0, 1], covs[..., 1, 1]
    det = a * d - b * b
    u, v = innovations[..., 0], innovations[..., 1]
    # Closed-form 2×2 inverse: avoids a LAPACK call per (observation, landmark).
    nis = (d * u * u - 2.0 * b * u * v + a * v * v) / det
    return nis, np.log(det)


def nearest_neighbour(
    nis: np.ndarray, log_det: np.ndarray, gate_assoc_chi2: float, require_unique: bool = False
) -> np.ndarray:
    """Gated nearest-neighbour pairing, one landmark per observation at most.

    Each observation picks the gated landmark (``nis < gate_assoc_chi2``) with
    the smallest normalised distance ``nis + ln|S|``; the ``ln|S|`` term stops
    uncertain landmarks from attracting observations only because their large
    ``S`` shrinks the NIS. When several observations pick the same landmark,
    the one with the smallest normalised distance keeps it and the others are
    left unpaired (they are then treated as new or ambiguous by the caller).

    Parameters
    ----------
    nis, log_det : ndarray, shape (K, L)
        From :func:`nis_2d` for every (observation, landmark) pair.
    gate_assoc_chi2 : float
        χ²₂ gate on the NIS (9.21 = 99 %).
    require_unique : bool
        Leave an observation unpaired when more than one landmark is inside
        its gate: picking the nearer of two plausible landmarks is a guess.

    Returns
    -------
    ndarray, shape (K,), int64
        Landmark index per observation or ``UNPAIRED``.
    """
    n_obs, n_lm = nis.shape
    pairing = np.full(n_obs, UNPAIRED, dtype=np.int64)
    if n_lm == 0:
        return pairing
    gated = nis < gate_assoc_chi2
    dist = np.where(gated, nis + log_det, np.inf)
    if require_unique:
        dist[gated.sum(axis=1) > 1] = np.inf
    best = np.argmin(dist, axis=1)
    best_dist = dist[np.arange(n_obs), best]
    # Visit observations from the most to the least certain match so that a
    # contested landmark goes to its closest observation.
    for k in np.argsort(best_dist, kind="stable"):
        if np.isfinite(best_dist[k]) and best[k] not in pairing:
            pairing[k] = best[k]
    return pairing


@dataclass(frozen=True, eq=False)
class JcbbResult:
    """Outcome of :func:`jcbb`.

    Attributes
    ----------
    pairing : ndarray, shape (K,), int64
        Landmark index per observation or ``UNPAIRED``.
    joint_nis : float
        Joint NIS ``D²`` of the chosen hypothesis (0 when nothing is paired).
    nodes : int
        Interpretation-tree nodes visited (cost diagnostic).
    exhausted : bool
        True when the search stopped at ``max_nodes`` and returned the best
        hypothesis found so far rather than the proven optimum.
    """

    pairing: np.ndarray
    joint_nis: float
    nodes: int
    exhausted: bool


def jcbb(
    n_obs: int,
    cand_obs: np.ndarray,
    cand_lm: np.ndarray,
    cand_innov: np.ndarray,
    cand_joint_cov: np.ndarray,
    confidence: float,
    max_nodes: int = 100_000,
    require_unique: bool = False,
) -> JcbbResult:
    """Joint Compatibility Branch and Bound over pre-gated candidate pairings.

    Searches the interpretation tree (observation ``k`` → one of its candidate
    landmarks, or unpaired) for the hypothesis with the most pairings whose
    joint NIS ``D² = nu_H^T S_H^-1 nu_H`` lies below ``χ²_{2k}(confidence)``;
    among hypotheses with as many pairings the smallest ``D²`` wins. A branch is
    cut when even pairing every remaining observation cannot beat the best
    hypothesis found so far.

    Parameters
    ----------
    n_obs : int
        Number of observations K.
    cand_obs, cand_lm : ndarray, shape (C,), int
        Observation and landmark index of each individually compatible candidate.
    cand_innov : ndarray, shape (C, 2)
        Innovation of each candidate (bearing wrapped).
    cand_joint_cov : ndarray, shape (2C, 2C)
        Joint innovation covariance of all candidates, block ``(a, b)`` being
        ``H_a P H_b^T`` plus the measurement noise on blocks of the same
        observation. Only blocks of candidates with distinct observations and
        distinct landmarks are ever read.
    confidence : float
        Probability of the joint gate, in (0, 1).
    max_nodes : int
        Search budget; see ``JcbbResult.exhausted``.
    require_unique : bool
        After the search, unpair every observation that could swap to another
        free candidate landmark with the hypothesis still jointly compatible:
        the data do not tell those two landmarks apart.

    Returns
    -------
    JcbbResult
    """
    cand_obs = np.asarray(cand_obs, dtype=np.int64)
    cand_lm = np.asarray(cand_lm, dtype=np.int64)
    # gates[k] bounds the joint NIS of k pairings (2k degrees of freedom).
    gates = np.concatenate(([0.0], chi2.ppf(confidence, 2 * np.arange(1, n_obs + 1))))
    # Try each observation's candidates best-first so that good hypotheses are
    # found early and bound the rest of the search.
    diag_nis, _ = nis_2d(cand_innov, _diag_blocks(cand_joint_cov))
    options = [
        [int(c) for c in sorted(np.flatnonzero(cand_obs == k), key=lambda c: diag_nis[c])]
        for k in range(n_obs)
    ]
    best = {"pairs": 0, "d2": 0.0, "chosen": []}
    nodes = 0

    def joint_d2(chosen: list[int]) -> float:
        idx = np.ravel([(2 * c, 2 * c + 1) for c in chosen])
        nu = cand_innov[chosen].ravel()
        try:
            chol = np.linalg.cholesky(cand_joint_cov[np.ix_(idx, idx)])
        except np.linalg.LinAlgError:
            return np.inf
        w = np.linalg.solve(chol, nu)
        return float(w @ w)

    def search(k: int, chosen: list[int], d2: float) -> None:
        nonlocal nodes
        nodes += 1
        if k == n_obs:
            if len(chosen) > best["pairs"] or (len(chosen) == best["pairs"] and d2 < best["d2"]):
                best.update(pairs=len(chosen), d2=d2, chosen=list(chosen))
            return
        if nodes >= max_nodes:
            return
        used = {int(cand_lm[c]) for c in chosen}
        for c in options[k]:
            if int(cand_lm[c]) in used:
                continue
            trial = chosen + [c]
            trial_d2 = joint_d2(trial)
            if trial_d2 < gates[len(trial)]:
                search(k + 1, trial, trial_d2)
        # Leave observation k unpaired only if the rest could still tie the best.
        if len(chosen) + (n_obs - k - 1) >= best["pairs"]:
            search(k + 1, chosen, d2)

    search(0, [], 0.0)
    chosen, d2 = best["chosen"], float(best["d2"])
    if require_unique and chosen:
        used = {int(cand_lm[c]) for c in chosen}
        swappable = [
            c for c in chosen
            if any(
                int(cand_lm[alt]) not in used
                and joint_d2([alt if x == c else x for x in chosen]) < gates[len(chosen)]
                for alt in options[cand_obs[c]]
            )
        ]
        chosen = [c for c in chosen if c not in swappable]
        d2 = joint_d2(chosen) if chosen else 0.0
    pairing = np.full(n_obs, UNPAIRED, dtype=np.int64)
    for c in chosen:
        pairing[cand_obs[c]] = cand_lm[c]
    return JcbbResult(pairing, d2, nodes, nodes >= max_nodes)


def _diag_blocks(joint_cov: np.ndarray) -> np.ndarray:
    """2×2 diagonal blocks of a (2C, 2C) matrix, shape (C, 2, 2)."""
    n = joint_cov.shape[0] // 2
    return joint_cov.reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :]
