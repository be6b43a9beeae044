# Learner, env and compiler services: CUDA runtime base (plus nvcc, which the env's tracer uses once to build
# its CUDA launchers; the build is cached under NAVI_CACHE_DIR on the artifacts volume).
# Build from the repository root: docker build -f deploy/cuda.Dockerfile .
FROM nvidia/cuda:12.6.3-cudnn-runtime-ubuntu24.04

ENV DEBIAN_FRONTEND=noninteractive \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:/usr/local/cuda/bin:$PATH \
    CUDA_HOME=/usr/local/cuda

RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv python3-dev build-essential git \
       cuda-nvcc-12-6 \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv $VIRTUAL_ENV

RUN pip install --no-cache-dir "torch>=2.5" --index-url https://download.pytorch.org/whl/cu126 \
    && pip install --no-cache-dir "setuptools>=68" "pybind11>=2.12" wheel

WORKDIR /app
COPY pyproject.toml ./
COPY navi ./navi
COPY shared ./shared
COPY services ./services
COPY benchmarks ./benchmarks
RUN pip install --no-cache-dir --no-build-isolation \
      ./shared/contracts ./shared/mesh ./services/compiler ./services/env ./services/learner ./services/auditor ./benchmarks . \
    && navi --version

EXPOSE 8000 9100
CMD ["navi", "serve", "learner"]
