#!/usr/bin/env bash
# The GPU lease's one command (docs/training.md, "The 15-minute lease"): on the lent machine, in the checkout, with
# packs/ carried. The script keeps its own deadlines (--budget-s, default 530 s); this timeout is the guarantee.
set -uo pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi -L 2>/dev/null || true
timeout -k 15 "${D2TURB_LEASE_TIMEOUT_S:-560}" python3 scripts/gpu_session.py --out "${OUT:?set OUT to the folder that comes back}" "$@"
