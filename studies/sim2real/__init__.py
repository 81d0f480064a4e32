"""Sim2Real learning, measured: the paper's Tables 2 and 3 on the virtual rig, and whether
the gap diagnosis' effects close the task gap better than domain randomisation.

``python -m studies.sim2real --out DIR`` (``pipeline.run``, stage by stage): what it
trains and on what (``plan``); the capture on the virtual rig (``capture``), its replays,
the diagnosis and the simulated protocols (``datasets``, with the compact fast-path
renderer ``plugin``); their arrays (``data``); the effects on the simulated images
(``augment``); the networks' inputs and targets (``features``); the models and their
training (``learn``), each run trained and evaluated (``study``); results.json's numbers
(``summary``); the tables and the figure (``report``). The learning libraries are the
optional extra ``tactile-sim[sim2real]``.
"""
