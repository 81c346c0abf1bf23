# fedhpg: one image for the server and the agents (CPU only).
# Where Docker Hub and PyPI are reachable (the defaults: the official slim Python base, CPU torch
# from PyTorch's CPU index):
#   docker build -t fedhpg .
# Offline, from a base and wheels made on this machine (docs/deploy.md; make image does both):
#   docker/make-base.sh && docker/make-wheelhouse.sh
#   docker build --network none --build-arg BASE_IMAGE=fedhpg-base:bookworm \
#       --build-arg PIP_SOURCE=wheelhouse -t fedhpg .
# The same file either way: the build arguments choose, nothing is edited. EXTRAS= (empty)
# leaves out Box2D and MuJoCo (LunarLander, HalfCheetah): 1.20 GB instead of 1.33 GB.

ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
# index: PyPI plus TORCH_INDEX; wheelhouse: only docker/wheelhouse/, no network.
ARG PIP_SOURCE=index
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
# envs: also Box2D and MuJoCo (LunarLander, HalfCheetah); empty: GridWorld and classic control.
ARG EXTRAS=envs
WORKDIR /src
COPY docker/wheelhouse /wheelhouse
COPY pyproject.toml constraints.txt ./
# The dependencies first, from pyproject.toml alone: this layer survives edits of the code.
RUN set -eu; \
    case "$PIP_SOURCE" in \
      index) echo "--extra-index-url $TORCH_INDEX" > pip-source.txt ;; \
      wheelhouse) printf -- '--no-index\n--find-links /wheelhouse\n' > pip-source.txt ;; \
      *) echo "PIP_SOURCE must be index or wheelhouse, not $PIP_SOURCE" >&2; exit 2 ;; \
    esac; \
    python3 -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
extras = [d for e in '$EXTRAS'.split(',') if e for d in p['optional-dependencies'][e]]; \
print(*p['dependencies'], *extras, sep='\n')" > requirements.txt; \
    python3 -m venv /opt/fedhpg; \
    /opt/fedhpg/bin/pip install --no-cache-dir --disable-pip-version-check \
        -r pip-source.txt -r requirements.txt -c constraints.txt
COPY README.md LICENSE ./
COPY fedhpg ./fedhpg
COPY common ./common
COPY envs ./envs
COPY server ./server
COPY agent ./agent
COPY conf ./conf
# The project as a wheel beside the environment, not in it: the final stage copies the
# environment (cached while the dependencies stay) and installs the wheel on top.
RUN /opt/fedhpg/bin/pip wheel --no-cache-dir --disable-pip-version-check --no-deps \
        -r pip-source.txt --wheel-dir /dist .

FROM ${BASE_IMAGE}
# Only the virtual environment and the project's wheel come over: no wheelhouse, no sources,
# no build tools.
RUN useradd --create-home --uid 1000 fedhpg && mkdir /runs && chown fedhpg /runs
COPY --from=build /opt/fedhpg /opt/fedhpg
COPY --from=build /dist /dist
RUN /opt/fedhpg/bin/pip install --no-cache-dir --disable-pip-version-check --no-deps \
        --no-index /dist/*.whl \
 && rm -rf /dist \
 && /opt/fedhpg/bin/python -c "import fedhpg.server.commands.server, fedhpg.agent.main, torch; \
assert torch.version.cuda is None, 'a CUDA build of torch: the image is CPU only'"
ENV PATH=/opt/fedhpg/bin:$PATH \
    OMP_NUM_THREADS=1 \
    MKL_NUM_THREADS=1 \
    PYTHONUNBUFFERED=1 \
    NUMBA_CACHE_DIR=/opt/fedhpg-numba
# The compiled engine's kernels, compiled once here (numba caches per CPU type: a host of
# another type compiles them again on first use, into the same directory).
RUN python -m fedhpg.common.learning.kernel_cache && chown -R fedhpg /opt/fedhpg-numba
USER fedhpg
WORKDIR /home/fedhpg
EXPOSE 5555
# /runs is where results go: mount a volume there (compose does; no VOLUME line, which would
# give every agent container an anonymous volume of its own). Hydra overrides follow the
# entrypoint, e.g. `docker run fedhpg fedhpg-agent agent.index=0 ...`.
CMD ["fedhpg-server", "server.bind_all=true", "server.out_dir=/runs/latest"]
