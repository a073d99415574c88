# shellcheck shell=bash
# Sourced by scripts/run, scripts/test, scripts/report and scripts/bench.
#
# Idempotent bootstrap of .venv at the repository root:
#   - create it when missing (or when it is broken);
#   - (re)install only when a requirements file, a package's setup.py /
#     setup.cfg / package.xml, or the Python version changed (a sha256 stamp);
#   - a clear message and a non-zero exit when Python is too old or an install fails.
# Then export the ROS environment every inkdiag process runs with: discovery
# stays on this machine's loopback interface, a domain id of its own unless the
# caller chose one, and the Fast DDS profile for large messages.

INKDIAG_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
INKDIAG_VENV="$INKDIAG_ROOT/.venv"
_inkdiag_py=${INKDIAG_PYTHON:-python3}

_inkdiag_die() { echo "inkdiag bootstrap: $*" >&2; exit 1; }

command -v "$_inkdiag_py" >/dev/null 2>&1 \
  || _inkdiag_die "'$_inkdiag_py' not found: install CPython >= 3.10 (or set INKDIAG_PYTHON)."
"$_inkdiag_py" - <<'PY' || _inkdiag_die "Python >= 3.10 is required; '$_inkdiag_py' is $("$_inkdiag_py" -V 2>&1). Set INKDIAG_PYTHON to a newer interpreter."
import sys
sys.exit(0 if sys.version_info >= (3, 10) else 1)
PY

_inkdiag_stamp_want=$(
  cd "$INKDIAG_ROOT" &&
  { "$_inkdiag_py" -V 2>&1
    cat requirements/*.txt \
        inkdiag_core/setup.py inkdiag_core/setup.cfg inkdiag_core/package.xml \
        msg_defs/setup.py msg_defs/setup.cfg msg_defs/package.xml \
        inkdiag_ros/setup.py inkdiag_ros/setup.cfg inkdiag_ros/package.xml
  } | sha256sum | cut -d' ' -f1
)
_inkdiag_stamp_file="$INKDIAG_VENV/.inkdiag-stamp"

if [ ! -x "$INKDIAG_VENV/bin/python" ] || ! "$INKDIAG_VENV/bin/python" -c 'import sys' >/dev/null 2>&1; then
  echo "inkdiag: creating $INKDIAG_VENV" >&2
  rm -rf "$INKDIAG_VENV"
  "$_inkdiag_py" -m venv "$INKDIAG_VENV" || _inkdiag_die "could not create the virtual environment $INKDIAG_VENV (is the python3-venv module installed?)"
fi

if [ "$(cat "$_inkdiag_stamp_file" 2>/dev/null)" != "$_inkdiag_stamp_want" ]; then
  _inkdiag_log="$INKDIAG_VENV/install.log"
  echo "inkdiag: installing ROS 2 Jazzy wheels, numpy/scipy/scikit-learn and the three packages into .venv (two to three minutes; log: $_inkdiag_log)" >&2
  _inkdiag_t0=$(date +%s)
  rm -f "$_inkdiag_stamp_file"
  if ! ( cd "$INKDIAG_ROOT" &&
         "$INKDIAG_VENV/bin/python" -m pip install --disable-pip-version-check \
             -r requirements/ros.txt -r requirements/dev.txt &&
         "$INKDIAG_VENV/bin/python" -m pip install --disable-pip-version-check \
             --config-settings editable_mode=compat \
             -e ./inkdiag_core -e ./msg_defs -e ./inkdiag_ros &&
         "$INKDIAG_VENV/bin/python" -m inkdiag_core._kernels ) >"$_inkdiag_log" 2>&1; then  # kernels compiled at install
    grep -v "^WARNING: Location" "$_inkdiag_log" | tail -n 25 >&2
    _inkdiag_die "installing into .venv failed (full log: $_inkdiag_log)"
  fi
  echo "$_inkdiag_stamp_want" >"$_inkdiag_stamp_file"
  echo "inkdiag: install done in $(( $(date +%s) - _inkdiag_t0 )) s" >&2
fi

export PATH="$INKDIAG_VENV/bin:$PATH"
export VIRTUAL_ENV="$INKDIAG_VENV"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
# Fast DDS on Linux: domain ids 0..101 stay clear of the ephemeral port range.
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( ($$ % 100) + 1 ))}"
export PYTHONUNBUFFERED=1
# Fast DDS 2.x (Jazzy): a 16 MB shared-memory segment for large trace messages (the
# default 512 kB holds one 400 kB message; see the profile's comment).
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$INKDIAG_ROOT/inkdiag_ros/inkdiag_ros/config/fastdds_profile.xml}"
