# Source this on a CUDA host without a package registry (a benchmark host): builds Navi's
# extensions in place, puts the packages on PYTHONPATH and defines a `navi` shell function.
# Needs torch (CUDA), numpy, nvcc, pybind11, setuptools, typer; pytest may come from artifacts/pytest-vendor.
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export PYTHONPATH=$root:$root/services/compiler:$root/services/env:$root/services/learner:$root/shared/contracts:$root/benchmarks:$root/artifacts/pytest-vendor:${PYTHONPATH:-}
export PYTHONUNBUFFERED=1
# Wheels carried in .whl/ (trimesh for procedural scenes) are unpacked once into a site folder: trimesh reads
# resource files beside its modules, which an import straight from the zip cannot.
if compgen -G "$root/.whl/*.whl" >/dev/null; then
  site=${NAVI_WHEEL_SITE:-/tmp/navi-site}
  [ -d "$site" ] || python -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$site" "$root"/.whl/*.whl
  export PYTHONPATH=$PYTHONPATH:$site
fi
for pkg in compiler env; do (cd "$root/services/$pkg" && python setup.py -q build_ext --inplace >/dev/null); done
navi() { python "$root/tests/navi_device.py" "$@"; }
