# syntax=docker/dockerfile:1
#
# pwlreg, the embedded service: API, worker processes, SQLite and artifacts under /data.
#
#   docker build -t pwlreg .
#   docker run -p 8000:8000 -v pwlreg-data:/data pwlreg
#
# Settings are PWLREG_* environment variables (see README), e.g. -e PWLREG_WORKERS=4.

ARG PYTHON_VERSION=3.11

# --- build: install the package and its dependencies into a virtual environment -------------
FROM python:${PYTHON_VERSION}-slim AS build

ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1

RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH

WORKDIR /src
# Dependencies first (a layer that changes only with pyproject.toml), then the code.
COPY pyproject.toml README.md ./
RUN mkdir core service \
    && touch core/__init__.py service/__init__.py \
    && pip install --upgrade pip \
    && pip install . \
    && pip uninstall -y pwlreg
COPY core ./core
COPY service ./service
RUN pip install --no-deps . \
    && python -c "import cv2, core.pipeline, service.app"

# --- runtime: the virtual environment only, as a non-root user ----------------------------------
FROM python:${PYTHON_VERSION}-slim AS runtime

LABEL org.opencontainers.image.title="pwlreg" \
      org.opencontainers.image.description="Piecewise-linear image registration as a REST service"

RUN groupadd --system --gid 10001 pwlreg \
    && useradd --system --uid 10001 --gid pwlreg --home-dir /data --no-create-home \
       --shell /usr/sbin/nologin pwlreg \
    && mkdir -p /data \
    && chown pwlreg:pwlreg /data

COPY --from=build /opt/venv /opt/venv

# numba compiles core's kernels on first use and caches them; the installed package is
# read-only for the service user, so the cache goes to a writable directory.
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    PWLREG_DATA_DIR=/data

USER pwlreg
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8000

# Ready = database, queue and data directory usable.
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=4).status == 200 else 1)"]

# SIGTERM: uvicorn drains requests, running jobs go back to the queue (nothing is lost).
STOPSIGNAL SIGTERM
CMD ["pwlreg", "serve", "--host", "0.0.0.0", "--port", "8000"]
