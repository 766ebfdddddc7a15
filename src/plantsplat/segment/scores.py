"""How two masks agree (light: neither numpy nor torch is imported here; both work)."""

from __future__ import annotations


def mask_iou(a, b) -> float:
    """Intersection over union of two bool masks of one shape (numpy arrays or torch tensors); 0 when both are empty.

    Example:
        >>> import numpy as np
        >>> mask_iou(np.array([True, True, False]), np.array([True, False, False]))
        0.5
    """
    union = float((a | b).sum())
    return float((a & b).sum()) / union if union > 0 else 0.0
