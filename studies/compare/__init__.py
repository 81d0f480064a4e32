"""The paper's Table 1 on a capture of the real rig: the fast path (each light field,
each background) and the physically based reference, each rendered at the capture's
measured poses, against the real images.

Modules, one concept each: ``table`` (per-tap MAE, SSIM and PSNR, full frame and in the
image circle, with bootstrap intervals over taps; table.json and table.md), ``run`` (the
renders: replays of the capture, the capture's alignment, the backgrounds),
``report`` (figures and report.html), ``taxim`` (Taxim, the peer simulator, through its
pip port) and ``taxim_table`` (its table refitted on the capture's presses), and ``cli``
(``tactile-sim compare``).
"""
