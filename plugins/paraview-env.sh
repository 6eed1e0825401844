#!/usr/bin/env bash
# Make Debian's ParaView (pvpython, pvbatch, mpiexec -n N pvbatch) load the vhm_viz plugin.
#
#   eval "$(bash plugins/paraview-env.sh)"      # from the project root
#
# Installs what is missing, quietly and only once:
#   * paraview, python3-paraview, openmpi-bin from apt when pvpython is absent;
#   * numba + llvmlite built for ParaView's Python and numpy, with --no-deps into
#     .paraview-site/ (a pip install with dependencies would pull a vtk wheel, and pvpython
#     then crashes on two VTKs); the project itself is used in place (PYTHONPATH);
#   * SimpleITK the same way, for the "VHM Medical Image Reader" (NIfTI, MetaImage,
#     NRRD/NHDR, DICOM in ITK's LPS frame, as vhm_viz.read_dataset places them);
#   * a sitecustomize.py shim: ParaView 5.11's plugin loader calls inspect.getargspec,
#     which Python 3.11 removed;
#   * the filters' numba kernels, compiled into ParaView's own numba cache
#     (vhm_viz.filters.warm; a stamp file marks it done).
# Then prints the export lines; everything else goes to stderr.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
site="${VHM_PARAVIEW_SITE:-$root/.paraview-site}"
say() { echo "paraview-env: $*" >&2; }

if ! command -v pvpython >/dev/null 2>&1 || ! command -v mpiexec >/dev/null 2>&1; then
    say "installing paraview, python3-paraview, openmpi-bin (apt)"
    sudo_cmd=""
    [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq >&2
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends \
        paraview python3-paraview openmpi-bin >&2
fi

# ParaView's Python is the system one: ask it for its version, numpy, and the numba of
# $site if any
read -r pyver npver have have_sitk < <(PYTHONPATH="$site" pvpython -c '
import sys, numpy
try:
    import numba
    have = numba.__version__
except Exception:
    have = "none"
try:
    import SimpleITK
    have_sitk = "yes"
except Exception:
    have_sitk = "no"
print(f"{sys.version_info[0]}.{sys.version_info[1]}", numpy.__version__, have, have_sitk)' \
    2>/dev/null | tail -n 1)
mkdir -p "$site"
case "$npver" in
    # numba 0.61 compiles the SIMD basis kernel (numba-level inlining) in about 10 s; 0.58
    # took over 10 minutes and 5 GB for the first resample, each MPI rank on its own
    1.2[4-6].*) numba_ver=0.61.2 llvmlite_ver=0.44.0 ;;
    1.2[2-3].*) numba_ver=0.58.1 llvmlite_ver=0.41.1
        say "numba 0.58 for numpy $npver: the first filter run compiles for over 10 minutes" ;;
    *) say "no known numba for ParaView's numpy $npver"; exit 1 ;;
esac
# pip_install PACKAGES...: wheels for ParaView's Python, without dependencies, into $site
pip_install() {
    local pip_python="" cand log
    for cand in "$root/.venv/bin/python" python3; do
        if "$cand" -m pip --version >/dev/null 2>&1; then pip_python="$cand"; break; fi
    done
    [ -n "$pip_python" ] || { say "no pip found (make the .venv first: bash .ci/setup)"; exit 1; }
    say "installing $* for Python $pyver into $site"
    log="$(mktemp)"
    if ! PIP_ROOT_USER_ACTION=ignore "$pip_python" -m pip install -q --no-deps \
        --disable-pip-version-check --only-binary=:all: --python-version "$pyver" \
        --implementation cp --platform manylinux2014_x86_64 --target "$site" --upgrade \
        "$@" >"$log" 2>&1; then
        cat "$log" >&2; rm -f "$log"; exit 1
    fi
    rm -f "$log"
}
if [ "$have" != "$numba_ver" ]; then
    # another version's files would stay next to the new ones
    rm -rf "$site"/numba "$site"/numba-*.dist-info "$site"/llvmlite "$site"/llvmlite-*.dist-info
    pip_install "numba==$numba_ver" "llvmlite==$llvmlite_ver"
    rm -rf "$site/numba_cache"  # compiled by the numba this replaces
fi
if [ "$have_sitk" != "yes" ]; then
    rm -rf "$site"/SimpleITK "$site"/[Ss]imple[Ii][Tt][Kk]-*.dist-info
    pip_install "SimpleITK>=2.3,<3"
fi
cat > "$site/sitecustomize.py" <<'PY'
# Written by plugins/paraview-env.sh: ParaView 5.11's Python plugin loader calls
# inspect.getargspec, removed in Python 3.11; getfullargspec has the same .args.
import inspect

if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec
PY

# numba compiles each kernel on its first call: about 70 s for the filters in a fresh
# cache, on every MPI rank at once. Compile them once here, into ParaView's own cache
# (kernels changed by a later edit of the project compile on their next first call)
# (tried once: a failure is reported, not retried on every eval)
stamp="$site/numba_cache/.compiled-numba-$numba_ver"
if [ ! -e "$stamp" ]; then
    say "compiling the filters' numba kernels once (about a minute and a half)"
    mkdir -p "$site/numba_cache"
    log="$(mktemp)"
    if PYTHONPATH="$root:$site" NUMBA_CACHE_DIR="$site/numba_cache" \
        pvpython -m vhm_viz.filters.warm >"$log" 2>&1; then
        touch "$stamp"
    else
        tail -n 5 "$log" >&2
        say "could not compile them ahead: the first filter run will (about 70 s)"
        echo "failed" > "$stamp"
        say "(delete $stamp to try again)"
    fi
    rm -f "$log"
fi

echo "export PYTHONPATH=\"$root:$site\${PYTHONPATH:+:\$PYTHONPATH}\""
echo "export PV_PLUGIN_PATH=\"$root/plugins\${PV_PLUGIN_PATH:+:\$PV_PLUGIN_PATH}\""
# ParaView's numba is another version than a virtual environment's: sharing one cache
# directory would make each invalidate the other's compiled code on every run
echo "export NUMBA_CACHE_DIR=\"$site/numba_cache\""
if [ "$(id -u)" -eq 0 ]; then  # Open MPI refuses root unless told
    echo "export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1"
fi
