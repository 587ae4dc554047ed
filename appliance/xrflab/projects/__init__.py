"""Student projects on the appliance: upload (checked, safely unpacked), sandboxed builds, runs.

- ``archive``: the archive checker and the safe unpacker.
- ``store``: projects and builds in SQLite (owner, source hash, toolchain, result, log).
- ``builder``: the build queue and the sandbox (unprivileged user, limits, no network).
- ``twentysim``: what the build page shows of a 20-sim controller (tokens and .info).
"""
