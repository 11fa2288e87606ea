# syntax=docker/dockerfile:1
#
# pwlreg, the embedded service: API, worker processes, SQLite and artifacts under /data.
#
#   docker build -t pwlreg .
#   docker run -p 8000:8000 -v pwlreg-data:/data pwlreg
#
# The same image runs the scale-out mode (Celery, Redis, PostgreSQL): see docker-compose.yml.
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
# The placeholder packages and setuptools' build directory go away with the layer: build/ would
# otherwise hold the empty placeholders, newer than the real files copied next.
RUN mkdir -p pwlreg core/formats service/api service/migrations/versions \
    && touch pwlreg/__init__.py core/__init__.py core/formats/__init__.py service/__init__.py \
       service/api/__init__.py service/migrations/__init__.py \
       service/migrations/versions/__init__.py \
    && pip install --upgrade pip \
    && pip install ".[scaleout]" \
    && pip uninstall -y pwlreg \
    && rm -rf build pwlreg core service ./*.egg-info
COPY pwlreg ./pwlreg
COPY core ./core
COPY service ./service
# The import check runs from / so that it sees the installed package, not the sources. The
# numba kernels are compiled here, once, into a cache the runtime stage keeps: a new container
# serves its first job without the few seconds of compilation (on another CPU model numba
# compiles again, into the same writable cache).
RUN pip install --no-deps . \
    && cd / && python -c "import cv2, pwlreg, pwlreg.core.pipeline, pwlreg.service.app, pwlreg.service.cli, pwlreg.service.celery_app" \
    && NUMBA_CACHE_DIR=/opt/numba-cache python -c "from pwlreg.core.pipeline import warm_up; warm_up()"

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
COPY --from=build --chown=pwlreg:pwlreg /opt/numba-cache /opt/numba-cache

ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    NUMBA_CACHE_DIR=/opt/numba-cache \
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
