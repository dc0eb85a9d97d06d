"""The human-study launcher: participants run through counterbalanced sessions of the VR tasks, with data that
survives any crash.

- :mod:`app.study.spec`: the study file (TOML): conditions, blocks, trials, practice, breaks, counterbalancing,
  quality thresholds; validated with one-line errors (:class:`~sonicverse_core.errors.StudyError`).
- :mod:`app.study.design`: balanced Latin squares (Williams) and least-filled assignment; a session's frozen plan.
- :mod:`app.study.store`: SQLite in WAL mode (synchronous=FULL), each trial committed when it ends, a CSV per
  session appended and fsynced per trial, a manifest per session; nothing is ever overwritten.
- :mod:`app.study.runner`: runs a session's plan from its first unfinished trial (headless with the simulated
  participant, or in the VR app with a person); pause, skip, abort; SIGINT/SIGTERM abort the running trial.
- :mod:`app.study.report`: per-participant and per-condition summaries and plots.
- :mod:`app.study.window`: the PyQt6 launcher window (everything it does is also a ``sonicverse study`` command).
"""
