"""Whether a trace holds a signal above its noise (numpy): the check before a fit that refuses
pure noise (``_checks.check_trace``), at the samples' own scale and at coarser ones.

A decay that moves for a small part of a long, noisy record (a block that halts after one
swing in the first 6 % of the window, at a noise of 7 % of its amplitude) hides within the
excursions of its samples' noise, yet stands far above it once w samples are averaged: the
noise of a mean of w falls as 1/sqrt(w) while a swing many samples long keeps its size.

Also the noise's scale itself (:func:`noise_sigma`, the white part from high differences) and
the running median that removes glitches (:func:`despike`), which the trace's analysis
(``_analysis``) reads too.
"""

from __future__ import annotations

import math

import numpy as np

from ._params import MAD


def despike(x: np.ndarray, width: int = 5) -> np.ndarray:
    """Running median over ``width`` samples: removes glitches of one or two samples."""
    if x.size < 3 * width:
        return x
    half = width // 2
    padded = np.concatenate([np.full(half, x[0]), x, np.full(half, x[-1])])
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, width), axis=1)


def noise_sigma(x: np.ndarray) -> float:
    """sigma of the white part of the noise: the MAD of the k-th differences (var =
    C(2k, k) sigma^2), the smallest over k = 2..5 (a smooth signal adds (w dt)^k A to the
    k-th differences, which the higher orders shed where the sampling is coarse), or, where
    it is below :data:`PREDICTION_SHARE` of that, the error of :func:`prediction_sigma`.

    At a few samples per period the differences measure the signal, not the noise: at 4.5
    samples per period they grow as (2 sin(w dt / 2))^k > 1, and a clean decay read as noise of
    0.8 of its amplitude (and was refused as "no free oscillation above the noise"). A sampled
    sinusoid is predicted exactly from its two previous samples at any step, so there the
    prediction error is the noise. Where the sampling is fine the two agree (both are the
    second differences' when w dt -> 0) and the differences stand.
    """
    if x.size < 8:
        return 0.0
    best, d = math.inf, np.diff(np.asarray(x, dtype=float))
    for k in range(2, 6):
        d = np.diff(d)
        s = float(MAD * np.median(np.abs(d - np.median(d))) / math.sqrt(math.comb(2 * k, k)))
        best = min(best, s)
    predicted = prediction_sigma(x)
    return predicted if predicted < PREDICTION_SHARE * best else best


#: the differences' noise gives way to the prediction error below this share of it: on pure
#: white noise (1,000 draws of 50-200 samples) the prediction error's sigma is at least 0.65 of
#: the differences' in 99 % of draws, 0.42 at the least (both estimate sigma)
PREDICTION_SHARE = 0.5


def prediction_sigma(x: np.ndarray) -> float:
    """sigma of white noise from the error of the least-squares linear prediction
    x[n+1] = a x[n] + b x[n-1] + c (an AR(2) with a level; var = (1 + a^2 + b^2) sigma^2, the
    MAD of the errors): exact for a sampled sinusoid at any step below Nyquist's, and close
    for a slow decay about a level that moves by jumps (friction's), whose few straddling
    errors the median ignores."""
    x = np.asarray(x, dtype=float)
    if x.size < 8:
        return 0.0
    scale = float(np.max(np.abs(x))) or 1.0
    y = x / scale
    A = np.stack([y[1:-1], y[:-2], np.ones(y.size - 2)], axis=1)
    coef = np.linalg.lstsq(A, y[2:], rcond=None)[0]
    err = y[2:] - A @ coef
    gain = 1.0 + coef[0] ** 2 + coef[1] ** 2
    return scale * float(MAD * np.median(np.abs(err - np.median(err))) / math.sqrt(gain))


#: the coarsest scale tried keeps at least this many block means
MIN_BLOCKS = 64
#: the block widths tried: 1, 4, 16, ... samples
SCALE_STEP = 4


def noise_excursion(n: int) -> float:
    """The largest half peak-to-peak, in noise sigmas, that pure white noise of ``n`` samples
    shows after the running median of :func:`despike`, with a margin: sqrt(2 ln n) + 1.

    The running median of five samples of white noise has a sd of 0.54 sigma, its half range
    over n samples stays below sqrt(2 ln n) sigma: simulated 99.9 % quantiles are 2.6, 2.5,
    2.8 and 3.0 sigma for n = 100, 1e3, 1e4 and 1e5 (the bound: 4.0, 4.7, 5.3, 5.8).
    """
    return math.sqrt(2.0 * math.log(max(n, 2))) + 1.0


def block_means(x: np.ndarray, w: int) -> np.ndarray:
    """The means of successive blocks of ``w`` samples (a last partial block dropped)."""
    n = (x.size // w) * w
    return x[:n].reshape(-1, w).mean(axis=1)


def excursions(x: np.ndarray) -> list[tuple[int, float, float]]:
    """The trace's half peak-to-peak against the noise's bound at each scale.

    At block widths w = 1, 4, 16, ... (at least :data:`MIN_BLOCKS` blocks), the half
    peak-to-peak of the block means (after :func:`despike`) and the noise sigma of those means
    from their own higher differences (``_analysis.noise_sigma``: a median, which the few
    blocks where a short motion curves do not move; correlated noise shows there as it is at
    that scale, not as its white part).

    Returns:
        [(w, half peak-to-peak, the bound noise_excursion(blocks) sigma_w)] for each scale.
    """
    x = np.asarray(x, dtype=float)
    out, w = [], 1
    while x.size // w >= MIN_BLOCKS or w == 1:
        xb = block_means(x, w)
        sigma = noise_sigma(xb)
        out.append((w, 0.5 * float(np.ptp(despike(xb))), noise_excursion(xb.size) * sigma))
        w *= SCALE_STEP
    return out


def above_noise(x: np.ndarray) -> bool:
    """Whether the trace stands above the excursions of pure noise at one of its scales
    (:func:`excursions`; a scale whose noise sigma is 0 counts as above only where the trace
    moves)."""
    return any(half > bound or (bound == 0.0 and half > 0.0)
               for _, half, bound in excursions(x))
