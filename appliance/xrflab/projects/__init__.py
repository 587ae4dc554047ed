"""Student projects on the appliance: upload (checked, safely unpacked), sandboxed builds, runs.

- ``archive``: the archive checker and the safe unpacker.
- ``store``: projects and builds in SQLite (owner, source hash, toolchain, result, log).
- ``builder``: the build queue; each build in a sandbox (unprivileged user, limits, no network):
  ``sandbox_launch``/``sandbox``/``sandbox_config``, ``build_user``, ``rt_core_mirror``,
  ``build_procs``, ``build_result``, ``build_key`` (reuse), ``build_log``, ``diagnostics``.
- ``twentysim``: what the build page shows of a 20-sim controller (tokens and .info).
"""
