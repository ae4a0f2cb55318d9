"""Middlebury stereo metrics: bad-t %, average absolute error, RMS, invalid share, on all and non-occluded pixels.

A prediction is "invalid" (a hole) where it is not finite. The dense bad-t figures count holes as bad, so a method
cannot look good by leaving its hard pixels empty; the sparse figures (`-sparse`) and the errors (avgerr, rms) are
over predicted pixels only. Only pixels with finite, positive ground truth take part.
"""

import numpy as np

THRESHOLDS = (0.5, 1.0, 2.0, 4.0)


def _fmt(t: float) -> str:
    return f"{t:g}"


def disparity_metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """Metrics over the pixels where `valid` (default: all) and the ground truth is known."""
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"disparity {pred.shape} and ground truth {gt.shape} differ in shape")
    region = np.isfinite(gt) & (gt > 0)
    if valid is not None:
        region &= np.asarray(valid, dtype=bool)
    n = int(region.sum())
    predicted = region & np.isfinite(pred)
    m = int(predicted.sum())
    err = np.abs(pred[predicted] - gt[predicted])
    out = {"pixels": n, "invalid": 100.0 * (n - m) / max(n, 1)}
    for t in THRESHOLDS:  # the figures over predicted pixels are None (JSON null) when none was predicted
        bad = int((err > t).sum())
        out[f"bad-{_fmt(t)}"] = 100.0 * (bad + n - m) / max(n, 1)
        out[f"bad-{_fmt(t)}-sparse"] = 100.0 * bad / m if m else None
    out["avgerr"] = float(err.mean()) if m else None
    out["rms"] = float(np.sqrt((err ** 2).mean())) if m else None
    return out


def evaluate(pred: np.ndarray, gt: np.ndarray, nonocc_mask: np.ndarray | None = None) -> dict:
    """{"all": metrics, "nonocc": metrics (only when a mask is given)}."""
    result = {"all": disparity_metrics(pred, gt)}
    if nonocc_mask is not None:
        result["nonocc"] = disparity_metrics(pred, gt, nonocc_mask)
    return result


def error_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """|pred - gt| with NaN where the ground truth is unknown and +inf where the prediction is a hole."""
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    err = np.abs(pred - gt)
    err[~np.isfinite(pred)] = np.inf
    err[~(np.isfinite(gt) & (gt > 0))] = np.nan
    return err


def format_table(rows: dict) -> str:
    """Markdown table: one row per (method, region) with the headline metrics."""
    cols = ["bad-0.5", "bad-1", "bad-2", "bad-4", "bad-2-sparse", "avgerr", "rms", "invalid"]
    lines = ["| method | region | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for method, result in rows.items():
        for region, m in result.items():
            lines.append(f"| {method} | {region} | " + " | ".join("-" if m[c] is None else f"{m[c]:.2f}"
                                                                 for c in cols) + " |")
    return "\n".join(lines)
