#!/usr/bin/env bash
# The README's quick start as a new user meets it: a fresh empty folder, a fresh clone of this checkout (its
# committed HEAD), and the README's two commands (demo, then tests) run verbatim in it by bash, with no virtual
# environment active. The commands are read from README.md's "## Quick start" section (its indented lines that
# start with "python3"), so this script cannot drift from what the README says.
#
#   scripts/check_quickstart.sh [WORKDIR]     # WORKDIR: where the fresh folder is made (default: mktemp -d)
#   QUICKSTART_PYTHON=/usr/bin/python3 scripts/check_quickstart.sh   # run the commands with that python3
#                                                                    # (e.g. Debian's externally-managed one)
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
work="${1:-$(mktemp -d)}"
mkdir -p "$work"
work="$(cd "$work" && pwd)"
if [ -n "$(ls -A "$work")" ]; then
    echo "error: $work is not empty (the quick start is checked in a fresh folder)" >&2
    exit 2
fi

# the README's commands: indented lines starting with python3 inside "## Quick start", up to the next "## "
mapfile -t commands < <(awk '/^## /{inside = ($0 == "## Quick start")} inside && /^    python3 /{sub(/^    /, ""); print}' \
    "$repo/README.md")
if [ "${#commands[@]}" -ne 2 ]; then
    echo "error: expected 2 commands in README.md's Quick start, found ${#commands[@]}" >&2
    exit 2
fi

if ! grep -qxF -- "${commands[1]}" "$repo/.ci/run"; then
    echo "error: .ci/run does not run the README's test command: ${commands[1]}" >&2
    exit 2
fi

unset VIRTUAL_ENV PYTHONPATH PYTHONHOME CONDA_PREFIX
if [ -n "${QUICKSTART_PYTHON:-}" ]; then  # put that interpreter first on PATH as python3
    mkdir -p "$work/.python3"
    ln -s "$(command -v "$QUICKSTART_PYTHON")" "$work/.python3/python3"
    export PATH="$work/.python3:$PATH"
fi
echo "== python3: $(command -v python3) ($(python3 --version 2>&1))"
git clone --quiet "$repo" "$work/d2turb"
echo "== fresh clone of $repo at $(git -C "$work/d2turb" log -1 --format='%h %s' | cut -c1-100) in $work/d2turb"
cd "$work/d2turb"
status=0
for cmd in "${commands[@]}"; do
    echo "== \$ $cmd"
    start=$SECONDS
    if bash -c "$cmd"; then
        echo "== ok ($((SECONDS - start)) s)"
    else
        rc=$?
        echo "== FAILED with status $rc ($((SECONDS - start)) s)"
        status=1
    fi
done
if [ -f demo_out/demo.png ]; then
    echo "== demo_out/demo.png: $(python3 -c 'import struct,sys; d=open(sys.argv[1],"rb").read(24); print("%dx%d PNG" % struct.unpack(">II", d[16:24]))' demo_out/demo.png)"
fi
du -sh .venv 2>/dev/null | sed 's/^/== virtual environment: /'
exit $status
