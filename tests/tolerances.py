"""Tolerances for comparing two runs of one float32 computation whose sums may be added up in another order."""
import numpy as np

FLOAT32_EPS = float(np.finfo(np.float32).eps)


def summation_order_tolerance(expected: np.ndarray, terms: int, amplification: float = 1.0) -> float:
    """Absolute tolerance between two float32 results whose sums of ``terms`` products ran in different orders.

    Reordering a float32 sum of n terms changes it by at most about ``n * eps * sum|terms|`` (the classic
    gamma_n bound); ``amplification`` carries that through what follows the sums (e.g. a solve's condition
    number).  The scale is the largest ``|expected|``: a sum's rounding follows the size of its terms, not of a
    result that cancelled to near zero, so a relative tolerance per element would be wrong for small elements.
    """
    return terms * FLOAT32_EPS * amplification * float(np.abs(expected).max())
