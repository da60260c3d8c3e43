# The RaFD serving image: FastAPI + onnxruntime (+ OpenVINO), no torch (only the `serve` extra is installed).
#   docker build -t rafd-serve .
#   docker build --build-arg EXTRAS=serve,live -t rafd-serve-live .   # + the Foxglove live view (--foxglove-port)
#   docker run --rm -p 8000:8000 --cpus 2 rafd-serve          # model threads follow --cpus (cgroup quota)
#   docker run --rm --network host -e RAFD_PORT=8001 rafd-serve  # another port: server and health check follow
#   docker run ... -e RAFD_MAX_STREAMS=512 -e RAFD_MODEL_PATH=/models/m.onnx -v $PWD/m.onnx:/models/m.onnx:ro rafd-serve
# One uvicorn process per container: a stream's 4-frame buffer lives in that process, so scale out with replicas
# behind a router that pins each stream id to one replica (deploy/: nginx `hash ... consistent`).
# Size (docs/deployment.md "Docker"): a multi-stage build, so the final image holds the virtual environment only: no pip cache,
# no build tree, no pip/setuptools, no torch checkpoint.

FROM python:3.11-slim AS build
# The extras installed: `serve` only by default; `serve,live` adds foxglove-sdk for the live view (+54 MB).
ARG EXTRAS=serve
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY rafd ./rafd
COPY service ./service
# The service runs the ONNX graph: the PyTorch checkpoint (rafd/assets/*.pt) is not needed in the image.
RUN rm -f rafd/assets/*.pt \
 && python -m venv /opt/venv \
 && /opt/venv/bin/pip install ".[${EXTRAS}]" \
 && /opt/venv/bin/pip uninstall -y -q pip setuptools
# Checks, run from / so they see the INSTALLED package (not /src): no torch in the image, the service imports
# none, both runtimes are there (onnxruntime fp32, OpenVINO for bf16), and the shipped default model is inside.
WORKDIR /
RUN /opt/venv/bin/python -c "import importlib.util as u; assert u.find_spec('torch') is None, 'torch installed'" \
 && /opt/venv/bin/python -c "import onnxruntime, openvino; print('runtimes:', onnxruntime.__version__, openvino.__version__)" \
 && /opt/venv/bin/python -c "import sys, service.app; assert 'torch' not in sys.modules" \
 && /opt/venv/bin/python -c "from rafd.assets import default_onnx; p = default_onnx(); assert p.is_file() and '/opt/venv/' in str(p), p; print('default model:', p)"

FROM python:3.11-slim
# PATH in full: an image without its own PATH (e.g. one made with `docker import`) would otherwise keep only the venv.
ENV PATH=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    RAFD_PORT=8000
COPY --from=build /opt/venv /opt/venv
RUN useradd --uid 10001 --no-create-home --shell /usr/sbin/nologin rafd
USER 10001
WORKDIR /tmp
EXPOSE 8000
# Ready = model loaded and warmed up; python's urllib, so the slim image needs no curl. RAFD_PORT moves the server
# and its health check together (e.g. several replicas with --network host).
HEALTHCHECK --interval=15s --timeout=3s --start-period=60s --retries=3 \
  CMD ["python", "-c", "import os, sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:%s/health/ready' % os.environ.get('RAFD_PORT', '8000'), timeout=2).status == 200 else 1)"]
CMD ["/bin/sh", "-c", "exec rafd-serve --host 0.0.0.0 --port \"$RAFD_PORT\""]
