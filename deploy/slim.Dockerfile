# The auditor service: a slim Python base with the CPU build of torch.
# Build from the repository root: docker build -f deploy/slim.Dockerfile .
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

RUN apt-get update \
    && apt-get install -y --no-install-recommends build-essential git \
    && rm -rf /var/lib/apt/lists/*

RUN pip install --no-cache-dir "torch>=2.5" --index-url https://download.pytorch.org/whl/cpu \
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

EXPOSE 8080 9100
CMD ["navi", "serve", "compiler"]
