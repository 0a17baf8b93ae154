# The page's JavaScript modules (three, @msgpack/msgpack), at the locked versions.
FROM node:20-slim AS web
WORKDIR /web
COPY client_web/package.json client_web/package-lock.json ./
RUN npm ci --no-audit --no-fund --omit=dev

# The wheel: the server, the protocol spec and the page with the module files it imports
# (package data, pyproject.toml), so the image runs the installed package, not a source tree.
FROM python:3.11-slim AS wheel
WORKDIR /src
COPY pyproject.toml README.md ./
COPY server ./server
COPY shared ./shared
COPY client_web ./client_web
COPY --from=web /web/node_modules ./client_web/node_modules
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM python:3.11-slim
# open3d needs libusb and OpenGL/OpenMP runtime libraries to import; serve restarts itself on
# jemalloc, which keeps a long-running server's memory flat (server/memory.py).
RUN apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 libgl1 \
    libjemalloc2 \
    && rm -rf /var/lib/apt/lists/*
COPY --from=wheel /wheels /wheels
RUN pip install --no-cache-dir /wheels/*.whl && rm -rf /wheels
ENV DRONESIM_HOST=0.0.0.0 DRONESIM_PORT=8000 DRONESIM_DATA_DIR=/data
WORKDIR /data
VOLUME /data
EXPOSE 8000
CMD ["python", "-m", "server", "serve"]
