"""Event-image metrics, following the EvDNeRF evaluation protocol.

Conventions (the paper's code, see ../shared/notes/evdnerf.md "Metrics protocol"):

* An event image is a log-brightness change dL (Eq. 5: C+ N+ - C- N-), float, signed.
* PSNR = 10 log10(data_range^2 / MSE) with data_range = 2 * max|E_val| taken over the whole
  validation set (not per image); stack metrics are the mean of the per-window values, as the
  paper's meters average per-image values.  We also give a pooled PSNR (one MSE over all
  windows), which is not dominated by windows without events.
* SSIM: Gaussian window 11x11, sigma 1.5, K1 = 0.01, K2 = 0.03, population (not sample)
  covariances, mean of the SSIM map over the pixels whose window lies fully inside the
  image.  This equals torchmetrics' StructuralSimilarityIndexMeasure (used by the paper) and
  skimage's structural_similarity(gaussian_weights=True, use_sample_covariance=False).
  Images smaller than 11 px use the largest odd window that fits (same sigma, renormalised).
* MAE: mean |pred - gt|.
* LPIPS needs pretrained AlexNet weights, which are not available here: it is not computed.
* Predictions are compared continuous (dL_hat) and quantised (Eq. 4, `quantize_log_change`).
* Every PSNR comes with its all-zero-prediction floor (PSNR of predicting "no events").

Finite-by-construction rules (no NaN / inf ever leaves this module):

* MSE == 0 (identical images) gives PSNR = PSNR_CAP_DB (100 dB) instead of +inf.
* A validation set without any event (max|gt| == 0) has no paper data range; `event_metrics`
  then uses data_range = 2 * max(C+, C-), the range of a one-event-per-pixel image, and says
  so in the result (`data_range_source`).
* Non-finite inputs or a data range that is not finite and > 0 raise InputError.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

PSNR_CAP_DB = 100.0
SSIM_WIN = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_float(name: str, a) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains NaN or inf values; metrics need finite images")
    return a


def _pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    pred = _as_float("prediction", pred)
    gt = _as_float("ground truth", gt)
    if pred.shape != gt.shape:
        raise InputError(f"prediction shape {pred.shape} differs from ground truth {gt.shape}")
    if pred.size == 0:
        raise InputError("empty images: nothing to compare")
    return pred, gt


def _check_range(data_range) -> float:
    r = float(data_range)
    if not (math.isfinite(r) and r > 0):
        raise InputError(f"data_range must be finite and > 0, got {data_range}")
    return r


def mse(pred, gt) -> float:
    pred, gt = _pair(pred, gt)
    return float(np.mean((pred - gt) ** 2))


def mae(pred, gt) -> float:
    """Mean absolute error over all elements."""
    pred, gt = _pair(pred, gt)
    return float(np.mean(np.abs(pred - gt)))


def _psnr_from_mse(m: float, r: float) -> float:
    if m <= 0.0:
        return PSNR_CAP_DB
    # log form: no overflow of r**2 / m for extreme values
    value = 20.0 * math.log10(r) - 10.0 * math.log10(m)
    return float(min(value, PSNR_CAP_DB))


def psnr(pred, gt, data_range: float) -> float:
    """10 log10(data_range^2 / MSE) over all elements; identical images give PSNR_CAP_DB."""
    r = _check_range(data_range)
    return _psnr_from_mse(mse(pred, gt), r)


def gaussian_kernel_1d(size: int = SSIM_WIN, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Normalised 1-D Gaussian taps exp(-x^2 / (2 sigma^2)), x = -(size//2) .. size//2."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    g = np.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return g / g.sum()


def _filter_valid(img: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation of (..., H, W) with g along both image axes (accumulated
    in place: half the time of summing temporaries, the same sums in the same order)."""
    n = g.size
    h, w = img.shape[-2:]
    rows = g[0] * img[..., 0:h - n + 1, :]
    for i in range(1, n):
        rows += g[i] * img[..., i:h - n + 1 + i, :]
    out = g[0] * rows[..., :, 0:w - n + 1]
    for j in range(1, n):
        out += g[j] * rows[..., :, j:w - n + 1 + j]
    return out


class _SsimReference:
    """What SSIM needs of the ground truth alone, computed once for every prediction scored
    against it (a prediction, its quantised version, the zero floor)."""

    def __init__(self, gt: np.ndarray, r: float):
        h, w = gt.shape[-2:]
        size = min(SSIM_WIN, h, w)
        if size % 2 == 0:
            size -= 1
        self.g = gaussian_kernel_1d(size, SSIM_SIGMA)
        self.c1 = (SSIM_K1 * r) ** 2
        self.c2 = (SSIM_K2 * r) ** 2
        self.mu_y = _filter_valid(gt, self.g)
        # (Co)variances are shift-invariant: compute them on values centred by the per-image mean
        # of gt, which keeps float64 cancellation small for large offsets (|values| ~ 1e6).
        self.m = gt.mean(axis=(-2, -1), keepdims=True)
        self.yc = gt - self.m
        self.myc = self.mu_y - self.m
        self.syy = _filter_valid(self.yc * self.yc, self.g) - self.myc * self.myc

    def maps(self, pred: np.ndarray) -> np.ndarray:
        """Per-image mean SSIM of pred against the reference -> array of shape (...)."""
        g, m = self.g, self.m
        mu_x = _filter_valid(pred, g)
        xc = pred - m
        mxc = mu_x - m
        sxx = _filter_valid(xc * xc, g) - mxc * mxc
        sxy = _filter_valid(xc * self.yc, g) - mxc * self.myc
        num = (2 * mu_x * self.mu_y + self.c1) * (2 * sxy + self.c2)
        den = (mu_x ** 2 + self.mu_y ** 2 + self.c1) * (sxx + self.syy + self.c2)
        return (num / den).mean(axis=(-2, -1))


def ssim(pred, gt, data_range: float) -> float:
    """Mean Gaussian-window SSIM of a 2-D image, or the mean over the images of a (..., H, W) stack."""
    r = _check_range(data_range)
    pred, gt = _pair(pred, gt)
    if pred.ndim < 2:
        raise InputError(f"SSIM needs images of shape (..., H, W), got shape {pred.shape}")
    return float(np.mean(_SsimReference(gt, r).maps(pred)))


def quantize_log_change(d_l, c_pos: float, c_neg: float) -> np.ndarray:
    """Eq. 4 quantisation: floor(max(dL,0)/C+) C+ - floor(max(-dL,0)/C-) C-, float64.

    I.e. the minimum number of events of each polarity the predicted change implies, turned
    back into a log change; |result| <= |dL| and it keeps the sign of dL.
    """
    if not (math.isfinite(c_pos) and math.isfinite(c_neg) and c_pos > 0 and c_neg > 0):
        raise InputError(f"contrast thresholds must be finite and > 0, got C+={c_pos}, C-={c_neg}")
    d_l = _as_float("log change", d_l)
    pos = np.floor(np.maximum(d_l, 0.0) / c_pos)
    neg = np.floor(np.maximum(-d_l, 0.0) / c_neg)
    return pos * c_pos - neg * c_neg


def protocol_windows(n_windows: int) -> np.ndarray:
    """Indices of the evaluated windows: 0, 4, 8, ... below n_windows - 1 (the last is skipped).

    n_windows <= 1 gives an empty selection.
    """
    n = int(n_windows)
    if n < 0:
        raise InputError(f"number of windows must be >= 0, got {n_windows}")
    return np.arange(0, max(n - 1, 0), 4, dtype=np.int64)


def _stack_scores(pred: np.ndarray, gt: np.ndarray, r: float, ssim_ref: _SsimReference) -> dict:
    per_mse = np.mean((pred - gt) ** 2, axis=(1, 2))
    per_psnr = [_psnr_from_mse(float(m), r) for m in per_mse]
    return {
        "psnr": float(np.mean(per_psnr)),
        "psnr_pooled": _psnr_from_mse(float(np.mean(per_mse)), r),
        "ssim": float(np.mean(ssim_ref.maps(pred))),
        "mae": float(np.mean(np.abs(pred - gt))),
        "psnr_per_window": [float(v) for v in per_psnr],
    }


def event_metrics(pred_stack, gt_stack, *, c_pos: float, c_neg: float,
                  data_range: float | None = None) -> dict:
    """Metrics of predicted vs ground-truth event images, (K, H, W) stacks of dL.

    Returns a dict with
      ``continuous``, ``quantized``: {psnr, psnr_pooled, ssim, mae, psnr_per_window} of the
        prediction as is and after Eq. 4 quantisation;
      ``zero_floor``: the same scores for an all-zero prediction (identical for both variants);
      ``data_range``, ``data_range_source`` ("given", "2*max|gt|" or "2*max(C+,C-): gt has no
        events"), ``n_windows``, ``lpips`` (None: weights unavailable).
    Pass ``data_range`` computed over the whole validation set when calling this per view.
    """
    pred, gt = _pair(pred_stack, gt_stack)
    if pred.ndim == 2:
        pred, gt = pred[None], gt[None]
    if pred.ndim != 3:
        raise InputError(f"event stacks must be (K, H, W), got shape {pred.shape}")
    if not (math.isfinite(c_pos) and math.isfinite(c_neg) and c_pos > 0 and c_neg > 0):
        raise InputError(f"contrast thresholds must be finite and > 0, got C+={c_pos}, C-={c_neg}")
    if data_range is not None:
        r, source = _check_range(data_range), "given"
    else:
        peak = float(np.max(np.abs(gt)))
        if peak > 0:
            r, source = 2.0 * peak, "2*max|gt|"
        else:
            r, source = 2.0 * max(c_pos, c_neg), "2*max(C+,C-): gt has no events"
    zero = np.zeros_like(gt)
    ref = _SsimReference(gt, r)
    return {
        "continuous": _stack_scores(pred, gt, r, ref),
        "quantized": _stack_scores(quantize_log_change(pred, c_pos, c_neg), gt, r, ref),
        "zero_floor": _stack_scores(zero, gt, r, ref),
        "data_range": r,
        "data_range_source": source,
        "n_windows": int(pred.shape[0]),
        "lpips": None,
        "lpips_note": "not computed: LPIPS needs pretrained AlexNet weights, not available",
    }


def _lstsq_affine(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    x = x.ravel()
    y = y.ravel()
    mx, my = x.mean(), y.mean()
    vx = float(np.mean((x - mx) ** 2))
    if vx <= 0.0:                    # constant prediction: only the offset can be fitted
        return 1.0, float(my - mx)
    a = float(np.mean((x - mx) * (y - my)) / vx)
    return a, float(my - a * mx)


def brightness_align(pred, gt, *, space: str = "linear", eps: float = 1e-3):
    """Least-squares affine brightness alignment of a rendered intensity to the ground truth.

    Event data fix brightness only up to an offset in log space (and a gain), so renders are
    aligned before intensity metrics, as in the paper's supplement.
      space="linear" (default): fit a, b minimising ||a*pred + b - gt||^2; return a*pred + b.
      space="log": fit on log(pred + eps) -> log(gt + eps) and return exp(a log(pred+eps) + b) - eps
        (a gain and gamma in linear space); inputs must be >= 0.
    Returns (aligned, a, b).  A constant prediction gets a = 1 and only the offset.
    """
    pred, gt = _pair(pred, gt)
    if space == "linear":
        a, b = _lstsq_affine(pred, gt)
        return a * pred + b, a, b
    if space == "log":
        if np.any(pred < 0) or np.any(gt < 0):
            raise InputError("log-space brightness alignment needs intensities >= 0")
        lp, lg = np.log(pred + eps), np.log(gt + eps)
        a, b = _lstsq_affine(lp, lg)
        return np.exp(np.clip(a * lp + b, -700.0, 700.0)) - eps, a, b
    raise InputError(f"brightness alignment space must be 'linear' or 'log', got {space!r}")
