#!/bin/sh
# The 60 s soak of the log path: tests/logs/test_continuity_10khz.py at full length (the suite runs
# it for 15 s). 10 kHz, 32 doubles, stress-ng on every core; passes when not one record is lost.
set -eu
cd "$(dirname "$0")/../.."
XRF_CONTINUITY_SECONDS="${XRF_CONTINUITY_SECONDS:-60}" exec ./lab test tests/logs/test_continuity_10khz.py -s "$@"
