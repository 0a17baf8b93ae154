# Base images pinned to exact releases, so a rebuild gets the same system; bump them on purpose.
# The page's JavaScript modules (three, @msgpack/msgpack), at the locked versions.
FROM node:20.18.1-bookworm-slim AS web
WORKDIR /web
COPY client_web/package.json client_web/package-lock.json ./
RUN npm ci --no-audit --no-fund --omit=dev

# The wheel: the server, the protocol spec and the page with the module files it imports
# (package data, pyproject.toml), so the image runs the installed package, not a source tree.
FROM python:3.11.11-slim-bookworm AS wheel
WORKDIR /src
COPY pyproject.toml README.md LICENSE THIRD_PARTY_NOTICES.md ./
COPY server ./server
COPY shared ./shared
COPY client_web ./client_web
COPY --from=web /web/node_modules ./client_web/node_modules
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM python:3.11.11-slim-bookworm
# EXTRAS: optional parts of the package, e.g. `docker build --build-arg EXTRAS=ray .` for the
# image the README's Ray cluster section runs (empty: the plain server).
ARG EXTRAS=""
# open3d needs libusb and OpenGL/OpenMP runtime libraries to import; serve restarts itself on
# jemalloc, which keeps a long-running server's memory flat (server/memory.py).
RUN apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 libgl1 \
    libjemalloc2 \
    && rm -rf /var/lib/apt/lists/*
COPY constraints.txt /tmp/constraints.txt
COPY --from=wheel /wheels /wheels
# Dependencies at the versions the suite passed with (constraints.txt, scripts/lock.py).
RUN wheel=$(ls /wheels/*.whl) \
    && pip install --no-cache-dir -c /tmp/constraints.txt "${wheel}${EXTRAS:+[$EXTRAS]}" \
    && rm -rf /wheels /tmp/constraints.txt
# The server runs as a user of its own, owning only its data volume.
RUN useradd --system --uid 10001 --home-dir /data --shell /usr/sbin/nologin dronesim \
    && mkdir -p /data && chown dronesim:dronesim /data
ENV DRONESIM_HOST=0.0.0.0 DRONESIM_PORT=8000 DRONESIM_DATA_DIR=/data
WORKDIR /data
VOLUME /data
USER dronesim
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=3)"]
CMD ["python", "-m", "server", "serve"]
