"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, and
how far it shrinks on held-out samples once that effect is added.

Modules, one concept each:

- the data: ``pairs`` (two datasets of one protocol, matched sample by sample),
  ``samples`` (which samples are compared and where), ``regions`` (where the error is);
  the image statistics themselves live in ``scenes.image_stats``, and ``metrics`` keeps
  the diagnosis' own (paired improvement, summaries, group means);
- the models: ``model`` (the fast simulator decomposed so that effects can be added),
  ``optics`` (the image-stage effects both models share and the working cameras),
  ``effects`` (the catalogue of candidate effects); for a reference-rendered dataset,
  ``physical`` (its catalogue of physical candidates), ``source_basis`` (its per-source
  renders), ``smoothing`` (the dent's smoothed change) and ``reference_model``;
- the diagnosis: ``fit`` (the fitter: a candidate's parameters on the training samples,
  from ``starts``, its starting points),
  ``judge`` (a fit on held-out samples, with intervals and significance), ``selection``
  (ranking, the tie and pair rules, forward selection), ``diagnosis`` (the three
  composed), ``diagnose`` (the run and its report's numbers), ``report`` (report.json and
  report.html);
- its blind validation: ``inject`` (the benchmark's own, independent injection of
  effects; its light in ``inject_light``, its image stages in ``inject_image``),
  ``unlike`` and ``described`` (mechanisms written unlike the catalogue, and
  from prose), ``benchmark`` and ``physical_benchmark`` (effects hidden in the reference);
  ``cli`` (the command).
"""
