"""Plant area density (PAD) from multi-scan TLS, AMAPVox style.

* :mod:`~vlsforest.pad.traverse` — shots of a TLS folder (:func:`load_tls_scans`, empty shots
  rebuilt from the scan pattern), the voxel traversal and its accumulators (:func:`accumulate`);
* :mod:`vlsforest.domain.leaf_angles` — leaf angle distributions and G(θ) (:func:`g_function`,
  re-exported here);
* :mod:`~vlsforest.pad.estimate` — the transmittance and bias-corrected FPL estimators
  (:func:`estimate_pad`) and the ``.vox`` export (:func:`pad_to_vox`);

Typical use::

    scans = load_tls_scans("plots/P1/tls")
    origin, shape = grid_for_scans(scans, 0.25, extent)
    acc = accumulate(scans, origin, 0.25, shape)
    pad, flags = estimate_pad(acc, lad="planophile", pad_max=5.0)
    write_vox("P1.vox", pad_to_vox(acc, pad, flags, 5.0))
"""

from vlsforest.domain.leaf_angles import LAD_NAMES, g_function, leaf_inclination_pdf
from vlsforest.pad.estimate import (
    ESTIMATORS,
    FLAG_CLIPPED,
    FLAG_FEW_PULSES,
    FLAG_SATURATED,
    FLAG_UNSAMPLED,
    estimate_pad,
    pad_to_vox,
    transmittance,
)
from vlsforest.pad.traverse import Accumulators, TlsScan, accumulate, grid_for_scans, load_tls_scans

__all__ = [
    "TlsScan", "Accumulators", "load_tls_scans", "grid_for_scans", "accumulate",
    "LAD_NAMES", "g_function", "leaf_inclination_pdf",
    "ESTIMATORS", "FLAG_UNSAMPLED", "FLAG_FEW_PULSES", "FLAG_SATURATED", "FLAG_CLIPPED",
    "estimate_pad", "transmittance", "pad_to_vox",
]
