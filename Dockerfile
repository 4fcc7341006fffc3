# syntax=docker/dockerfile:1
# scandiff as a wheel in a slim image, run by an unprivileged user. One image for every role:
#   docker run IMAGE                      -> scandiff serve (API + embedded workers, SQLite)
#   docker run IMAGE scandiff serve --workers 0 / scandiff worker  (see docker-compose.yml)
# Settings are SCANDIFF_* environment variables (docs/deployment.md).
ARG PYTHON_VERSION=3.12

# --- build: the project and every dependency as wheels (no compiler reaches the final image)
FROM python:${PYTHON_VERSION}-slim AS build
# a C compiler for the localiser's plane-fit and k-nearest-neighbour kernels (setup.py; optional:
# without one the wheel falls back to numpy / pykdtree, the same results, slower at 1M points)
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
# app/static and app/migrations are symlinks to these two: the wheel gets real files.
COPY pyproject.toml setup.py README.md ./
COPY static ./static
COPY migrations ./migrations
COPY app ./app
RUN pip wheel --no-cache-dir --wheel-dir /wheels '.[postgres,redis]'

# --- runtime
FROM python:${PYTHON_VERSION}-slim
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    VIRTUAL_ENV=/opt/scandiff \
    PATH=/opt/scandiff/bin:$PATH \
    SCANDIFF_DATA_DIR=/var/lib/scandiff \
    SCANDIFF_HOST=0.0.0.0 \
    SCANDIFF_PORT=8000

RUN groupadd --system --gid 10001 scandiff \
    && useradd --system --uid 10001 --gid scandiff --home-dir /var/lib/scandiff \
       --no-create-home --shell /usr/sbin/nologin scandiff \
    && install -d -o scandiff -g scandiff -m 0750 /var/lib/scandiff

# Installed from the build stage's wheels only (--no-index): not editable, no source tree.
RUN --mount=type=bind,from=build,source=/wheels,target=/wheels \
    python -m venv /opt/scandiff \
    && /opt/scandiff/bin/pip install --no-cache-dir --no-index --find-links /wheels \
       'scandiff[postgres,redis]'

USER scandiff
WORKDIR /var/lib/scandiff
# Declared after the chown: a fresh named volume starts out owned by scandiff.
VOLUME ["/var/lib/scandiff"]
EXPOSE 8000

# 200 while the database works (503 otherwise): urllib raises on anything but 2xx.
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/api/v1/health' % os.environ.get('SCANDIFF_PORT', '8000'), timeout=4)"]

CMD ["scandiff", "serve"]
