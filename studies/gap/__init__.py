"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, and
how far it shrinks on held-out samples once that effect is added.

Modules, one concept each: ``pairs`` (two datasets of one protocol, matched sample by
sample), ``metrics`` (MAE, SSIM, PSNR, bootstrap intervals), ``regions`` (where the error
is), ``model`` (the fast simulator decomposed so that effects can be added),
``effects`` (the catalogue of candidate effects), ``fit`` (fitting, ranking and forward
selection), ``report`` (report.json and report.html), ``inject`` (the benchmark's own,
independent injection of effects) and ``benchmark`` (blind validation).
"""
