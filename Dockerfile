# The mmsclean web app. Build: docker compose build; run: docker compose up (port 8000).
FROM python:3.11-slim

RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/mmsclean
COPY pyproject.toml requirements.lock README.md ./
COPY app ./app
COPY frontend_assets ./frontend_assets
COPY models ./models
COPY data_samples ./data_samples
# torch from the CPU index: the default PyPI wheel pulls several GB of CUDA libraries.
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
 && pip install --no-cache-dir -c requirements.lock .

ENV MMSCLEAN_DATA_DIR=/data \
    MMSCLEAN_WEIGHTS_DIR=/opt/mmsclean/weights \
    MMSCLEAN_SAMPLE_DIR=/opt/mmsclean/data_samples/urban-60m \
    MMSCLEAN_HOST=0.0.0.0 \
    MMSCLEAN_PORT=8000
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/health')"
CMD ["mmsclean", "serve", "--host", "0.0.0.0", "--port", "8000"]
