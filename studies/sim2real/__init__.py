"""Sim2Real learning, measured: the paper's Tables 2 and 3 on the virtual rig, and whether
the gap diagnosis' effects close the task gap better than domain randomisation.

``python -m studies.sim2real --out DIR`` (``study.run``): the data (``data``, the compact
fast-path renderer ``plugin``), the effects on the simulated images (``augment``), the
models and their training (``learn``), the tables and the figure (``report``). The
learning libraries are the optional extra ``tactile-sim[sim2real]``.
"""
