#!/bin/sh
# celld's two entry points for a new machine; each sets itself up first.
#   ./run.sh demo   the main job on the simulated cell
#   ./run.sh test   the test suite (what CI runs)
# Set-up: libusb-1.0 (open3d needs it on Debian), a virtual environment in
# .venv/ and the package with its dependencies at the versions of
# constraints.txt. Re-running is cheap: the install is redone only when
# pyproject.toml or constraints.txt changes.
set -eu
cd "$(dirname "$0")"

need_root() {
    echo "celld set-up: $1 is missing. Run as root, or install it first with:" >&2
    echo "    sudo apt-get update && sudo apt-get install -y $2" >&2
    exit 1
}

apt_install() {
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        echo "celld set-up: installing $*" >&2
        apt-get update -qq >&2
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >&2
    else
        need_root "$1" "$*"
    fi
}

pick_python() {
    for py in "${PYTHON:-}" python3.11 python3; do
        [ -n "$py" ] || continue
        if command -v "$py" >/dev/null 2>&1 &&
            "$py" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
            echo "$py"; return 0
        fi
    done
    echo "celld set-up: Python 3.11 is required (python3.11 not found on PATH)" >&2
    exit 1
}

ensure_libusb() {
    if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so'; then return 0; fi
    for d in /lib /usr/lib /lib64 /usr/lib64 /usr/lib/x86_64-linux-gnu /lib/x86_64-linux-gnu; do
        ls "$d"/libusb-1.0.so* >/dev/null 2>&1 && return 0
    done
    apt_install libusb-1.0-0
}

ensure_venv() {
    stamp=.venv/.celld-installed
    if [ -x .venv/bin/python ] && [ -f "$stamp" ] && [ "$stamp" -nt pyproject.toml ] && [ "$stamp" -nt constraints.txt ]; then
        return 0
    fi
    py=$(pick_python)
    if [ ! -x .venv/bin/python ]; then
        if ! "$py" -m venv .venv >/dev/null 2>&1; then
            rm -rf .venv
            apt_install python3.11-venv
            "$py" -m venv .venv
        fi
    fi
    # Against the versions the suite passed with (constraints.txt), not whatever the index has today;
    # with CELLD_WHEELHOUSE (made by ./run.sh wheelhouse DIR) from that directory alone, no index.
    if [ -n "${CELLD_WHEELHOUSE:-}" ]; then
        echo "celld set-up: installing celld and its dependencies into .venv/ from $CELLD_WHEELHOUSE (no index)" >&2
        .venv/bin/python -m pip install -q --no-index --find-links "$CELLD_WHEELHOUSE" -c constraints.txt -e '.[test]' >&2
    else
        echo "celld set-up: installing celld and its dependencies into .venv/ (first run takes a few minutes)" >&2
        .venv/bin/python -m pip install -q --upgrade pip >&2
        .venv/bin/python -m pip install -q -c constraints.txt -e '.[test]' >&2
    fi
    touch "$stamp"
}

cmd=${1:-}
[ $# -gt 0 ] && shift
case "$cmd" in
    demo)
        ensure_libusb; ensure_venv
        exec .venv/bin/celld demo "$@" ;;
    test)
        ensure_libusb; ensure_venv
        # With arguments, one pytest run of them. Without, two passes: everything but the simulated
        # cells and the motion process's real-time tests on two workers, then those one at a time in
        # one process: their 2 ms loops miss cycles when anything else runs beside them on two cores.
        if [ $# -gt 0 ]; then
            exec .venv/bin/python -m pytest -m "not hardware" "$@"
        fi
        status=0
        .venv/bin/python -m pytest -m "not hardware and not cell and not realtime" || status=$?
        .venv/bin/python -m pytest -m "(cell or realtime) and not hardware" -n 0 || status=$?
        exit "$status" ;;
    setup)
        ensure_libusb; ensure_venv ;;
    wheelhouse)
        # Every wheel a cell PC without internet needs, at constraints.txt's versions: celld's own, its
        # dependencies, the test tools and the build back-end of the editable install. Copy DIR there
        # with the checkout and run CELLD_WHEELHOUSE=DIR ./run.sh setup (or pip install --no-index
        # --find-links DIR celld, for the package alone).
        [ $# -eq 1 ] || { echo "usage: ./run.sh wheelhouse DIR" >&2; exit 2; }
        ensure_libusb; ensure_venv
        .venv/bin/python -m pip wheel -q -c constraints.txt -w "$1" '.[test]' setuptools wheel >&2
        echo "celld wheelhouse: $(ls "$1" | wc -l) wheels in $1" >&2 ;;
    *)
        echo "usage: ./run.sh demo|test|setup|wheelhouse [args...]" >&2
        exit 2 ;;
esac
