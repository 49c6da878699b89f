# Source this file: it makes sure the build's packages and the virtualenv exist (scripts/setup.sh,
# without the tests' part) and exports what cargo and the built binaries need to find libtorch. Respects BWM_VENV and CARGO_TARGET_DIR.
BWM_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export BWM_VENV="${BWM_VENV:-$BWM_ROOT/.venv}"
bash "$BWM_ROOT/scripts/setup.sh" || return 1 2>/dev/null || exit 1
export TORCHINDUCTOR_CACHE_DIR="${TORCHINDUCTOR_CACHE_DIR:-$BWM_VENV/.torchinductor}"
export VIRTUAL_ENV="$BWM_VENV"
export PATH="$BWM_VENV/bin:$PATH"
export LIBTORCH_USE_PYTORCH=1
BWM_TORCH_LIB="$("$BWM_VENV/bin/python" -c 'import torch,os;print(os.path.join(os.path.dirname(torch.__file__),"lib"))')"
export LD_LIBRARY_PATH="$BWM_TORCH_LIB${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
