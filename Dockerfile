# One image for every drivebench process: compose.yaml picks the process by its command.
#   docker compose build                          # CPU torch (small image; the explicit brain needs no torch)
#   TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128 docker compose build   # on a GPU host
# BASE_IMAGE may name any Debian-like image with Python >= 3.11 and venv (python:3.11-slim-bookworm by default).
ARG BASE_IMAGE=python:3.11-slim-bookworm

FROM ${BASE_IMAGE} AS build
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
# The image always has the whole stack (drivebench[stack]). EXTRAS adds to it: ml, neural brains (torch,
# onnxruntime); gl, the fast renderer (moderngl, Mesa's EGL); board, the challenge server (Starlette, uvicorn, and
# Debian's bubblewrap for its sandbox). EXTRAS="" gives a small image for the explicit brain and the rest (PyBullet's
# renderer only).
ARG EXTRAS=ml,gl,board
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
# A compiler only for packages without a wheel for this platform (pybullet on some architectures).
RUN apt-get update && apt-get install -y --no-install-recommends build-essential \
    && rm -rf /var/lib/apt/lists/*
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# torch first, from the chosen index: a plain requirement would take PyPI's multi-GB CUDA build on x86-64.
RUN case ",${EXTRAS}," in *,ml,*) pip install --index-url "${TORCH_INDEX_URL}" torch ;; esac
WORKDIR /src
COPY pyproject.toml README.md ./
COPY protocol protocol
COPY circuits circuits
COPY services services
COPY brains brains
COPY recorder recorder
COPY orchestrator orchestrator
COPY drivebench drivebench
# orchestrator/experiments links here: the wheel carries the matrix files that commands default to.
COPY experiments experiments
RUN pip install ".[stack${EXTRAS:+,${EXTRAS}}]"
# Smaller by ~290 MB: pybullet's wheel carries 126 MB of debug symbols and ~170 MB of example robots, meshes and
# environments (pybullet_data, _envs, _examples, _robots, _utils) that drivebench never loads: it builds its own scene.
RUN site=$(python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])") \
    && rm -rf "$site"/pybullet_data "$site"/pybullet_envs "$site"/pybullet_examples "$site"/pybullet_robots \
       "$site"/pybullet_utils \
    && strip --strip-unneeded "$site"/pybullet*.so \
    && python -c "import pybullet; pybullet.connect(pybullet.DIRECT); pybullet.disconnect()"

FROM ${BASE_IMAGE}
ARG EXTRAS=ml,gl,board
# libgomp: torch's and OpenCV's thread pools; tini is compose's `init: true`, no package needed. With the gl extra,
# EGL and Mesa's llvmpipe (~145 MB, LLVM most of it) for --renderer gl without a GPU (DRIVEBENCH_RENDERER in compose).
# With the board extra, bubblewrap (~150 kB): the challenge server refuses to start without its sandbox.
RUN case ",${EXTRAS}," in *,gl,*) gl="libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgbm1" ;; *) gl="" ;; esac \
    && case ",${EXTRAS}," in *,board,*) board="bubblewrap" ;; *) board="" ;; esac \
    && apt-get update && apt-get install -y --no-install-recommends libgomp1 $gl $board \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH PYTHONUNBUFFERED=1 MPLBACKEND=Agg \
    DRIVEBENCH_ROUTER=tcp/127.0.0.1:7447 DRIVEBENCH_RUN_ID=compose
WORKDIR /app
COPY experiments experiments
COPY deploy deploy
# Not root: a process reachable over the bus must not own the machine. compose runs every service as
# DRIVEBENCH_UID:DRIVEBENCH_GID (default 1000:1000, the usual first user) so that what lands in the bind-mounted
# ./results belongs to you; alone, the image runs as its own user `drivebench` (uid 1000). HOME is /tmp: an
# arbitrary uid has no home, and matplotlib and torch want a writable cache.
RUN useradd --uid 1000 --user-group --no-create-home --home-dir /tmp --shell /usr/sbin/nologin drivebench \
    && mkdir -p /results && chown drivebench:drivebench /results
ENV HOME=/tmp MPLCONFIGDIR=/tmp/matplotlib
USER drivebench
# Results, recordings and matrices go to /results (a mounted folder in compose.yaml).
VOLUME /results
# Every service's command overrides this; alone, the image drives one episode on a local stack.
CMD ["drivebench", "run", "--runs-dir", "/results/runs"]
