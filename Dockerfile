# relightcli runtime image: ONNX Runtime + Embree on the CPU, no torch, no training code.
#   docker build -t relightcli .
#   docker run --rm -v "$PWD/in:/in" -v "$PWD/out:/out" relightcli /in --hdr /in/sky.hdr -o /out

FROM python:3.11-slim-bookworm AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md requirements.lock ./
COPY relightcli ./relightcli
# The models go into the wheel as package data (relightcli/models in site-packages)
COPY models ./models
RUN python -m venv /opt/venv \
 && /opt/venv/bin/pip install --no-compile -c requirements.lock . \
 && /opt/venv/bin/python -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)"

FROM python:3.11-slim-bookworm AS runtime
# One Debian package beyond the base image: numba's OpenMP threading layer links libgomp
# (we run numba's kernels on our own threads, but every library a wheel ships must load);
# otherwise the wheels load only libc, libstdc++, libgcc and zlib from the system
# (tests/test_runtime_env.py checks this with ldd + dpkg).
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
    libgomp1 \
 && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/venv /opt/venv
# numba caches the compiled integrator kernels here (site-packages is not writable at run
# time); the cache is filled below, as the user that runs, so a container loads the kernels
# (~0.2 s) instead of compiling them (~7-9 s; again only on a CPU unlike the build's)
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    NUMBA_CACHE_DIR=/opt/numba-cache
RUN useradd --create-home --uid 10001 relight \
 && mkdir -p /opt/numba-cache && chown relight /opt/numba-cache \
 && relight --version && relight info
USER relight
RUN python -c "from relightcli.render.integrator import compile_kernels; assert compile_kernels()"
WORKDIR /work
ENTRYPOINT ["relight"]
CMD ["--help"]
