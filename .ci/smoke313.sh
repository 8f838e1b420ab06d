#!/usr/bin/env bash
# Kept for old notes: the Python 3.13 smoke path is `.ci/smoke.sh 3.13`.
exec "$(dirname "$0")/smoke.sh" 3.13 "$@"
