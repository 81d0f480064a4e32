"""Which light field brings the fast Phong path closest to physically guided light?

The study (its design: ``study``'s docstring; ``python -m studies.pbr_field_comparison``)
in modules, one concept each: ``contacts`` (the contacts' depth maps on our membrane),
``frames`` (the fast path's and the reference's frames, ``Settings``), ``calibration``
(gain and offset onto the reference), ``metrics`` (per-contact metrics and the pixels
they are taken over), ``summary`` (bootstrap means, the best field, the conclusion),
``regions`` (where each field fails, by class of region), ``report`` (summary.md),
``figures`` and ``study`` (``run`` and ``main``).

Re-exported here: the names tests/test_pbr_study.py reads as ``study.<name>``, each from
its one module.
"""

from .calibration import fit_affine, fit_gain, leave_one_out_calibration
from .contacts import (NO_CONTACT, PUBLISHED, QUICK_CONTACTS, analytic_contacts, published_contacts, refusal,
                       rig_contacts, surface_taps)
from .frames import CACHE_FOLDER, QUICK, Settings, check_settings, downsample, reference_frame
from .metrics import CHANGE_KINDS, CORRELATION, KINDS, METRICS, change_metrics, reliable_pixels
from .regions import contact_region_table, failures, region_errors
from .study import JSON_NAME, run
from .summary import bootstrap_mean

__all__ = ["CACHE_FOLDER", "CHANGE_KINDS", "CORRELATION", "JSON_NAME", "KINDS", "METRICS", "NO_CONTACT", "PUBLISHED",
           "QUICK", "QUICK_CONTACTS", "Settings", "analytic_contacts", "bootstrap_mean", "change_metrics",
           "check_settings", "contact_region_table", "downsample", "failures", "fit_affine", "fit_gain",
           "leave_one_out_calibration", "published_contacts", "reference_frame", "refusal", "region_errors",
           "reliable_pixels", "rig_contacts", "run", "surface_taps"]
