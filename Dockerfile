# One image for api, worker, beat and migrate (docker-compose.yml picks the command).
FROM python:3.11-slim
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PYTHONPATH=/app \
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
WORKDIR /app
COPY pyproject.toml ./
COPY svrobs_core ./svrobs_core
COPY svrobs_lab ./svrobs_lab
COPY service ./service
COPY worker ./worker
COPY migrations ./migrations
RUN pip install . && useradd --create-home svrobs && mkdir -p /var/lib/svrobs \
    && chown svrobs /var/lib/svrobs
USER svrobs
EXPOSE 8000
CMD ["uvicorn", "service.app:app", "--host", "0.0.0.0", "--port", "8000"]
