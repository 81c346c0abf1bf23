# fedhpg: one image for the server and the agents (CPU only).
# Build: docker build -t fedhpg .      Run: see docker-compose.yml and README "Deploy".

FROM python:3.11-slim AS build
WORKDIR /src
COPY pyproject.toml README.md constraints.txt ./
COPY common ./common
COPY envs ./envs
COPY server ./server
COPY agent ./agent
COPY conf ./conf
# CPU wheels of torch come from PyTorch's CPU index; everything else from PyPI, pinned.
RUN python -m venv /opt/fedhpg \
 && /opt/fedhpg/bin/pip install --no-cache-dir --upgrade pip \
 && /opt/fedhpg/bin/pip install --no-cache-dir --extra-index-url https://download.pytorch.org/whl/cpu \
        -c constraints.txt ".[envs]"

FROM python:3.11-slim
RUN useradd --create-home --uid 1000 fedhpg && mkdir /runs && chown fedhpg /runs
COPY --from=build /opt/fedhpg /opt/fedhpg
ENV PATH=/opt/fedhpg/bin:$PATH \
    OMP_NUM_THREADS=1 \
    MKL_NUM_THREADS=1 \
    PYTHONUNBUFFERED=1
USER fedhpg
WORKDIR /home/fedhpg
VOLUME ["/runs"]
EXPOSE 5555
# Hydra overrides follow the entrypoint, e.g. `docker run fedhpg fedhpg-agent agent.index=0 ...`.
CMD ["fedhpg-server", "server.bind_all=true", "server.out_dir=/runs/latest"]
