# syntax=docker/dockerfile:1
# The RaFD serving image: FastAPI + onnxruntime, no torch (only the `serve` extra is installed).
#   docker build -t rafd-serve .
#   docker run --rm -p 8000:8000 --cpus 2 rafd-serve          # onnxruntime threads follow --cpus
#   docker run ... -e RAFD_MAX_STREAMS=512 -e RAFD_MODEL_PATH=/models/m.onnx -v $PWD/m.onnx:/models/m.onnx:ro rafd-serve
# One uvicorn process per container: a stream's 4-frame buffer lives in that process, so scale out
# with replicas behind a router that pins each stream_id to one replica.

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY rafd ./rafd
COPY service ./service
# Checks: no torch in the image, the service imports none, both runtimes are there (onnxruntime fp32, OpenVINO
# for bf16), and the shipped default model is inside.
RUN python -m venv /opt/venv \
 && /opt/venv/bin/pip install ".[serve]" \
 && /opt/venv/bin/python -c "import importlib.util as u; assert u.find_spec('torch') is None, 'torch installed'" \
 && /opt/venv/bin/python -c "import onnxruntime, openvino; print('runtimes:', onnxruntime.__version__, openvino.__version__)" \
 && /opt/venv/bin/python -c "import sys, service.app; assert 'torch' not in sys.modules" \
 && /opt/venv/bin/python -c "from rafd.assets import default_onnx; print('default model:', default_onnx())"

FROM python:3.11-slim
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1
COPY --from=build /opt/venv /opt/venv
RUN useradd --system --uid 10001 --no-create-home --shell /usr/sbin/nologin rafd
USER rafd
EXPOSE 8000
# Ready = model loaded and warmed up; python's urllib, so the slim image needs no curl.
HEALTHCHECK --interval=15s --timeout=3s --start-period=60s --retries=3 \
  CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/health/ready', timeout=2).status == 200 else 1)"]
CMD ["rafd-serve", "--host", "0.0.0.0", "--port", "8000"]
