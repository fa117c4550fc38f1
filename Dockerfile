# One image for the migrate, api, worker and beat services of docker-compose.yml (each
# service picks its command there); see docs/deploy.md. tests/deploy/test_image.py
# builds what these lines build and starts every compose service from it.
FROM python:3.11-slim
# The commit recorded in each job's provenance (docker-compose.yml passes it as a build arg).
ARG SVROBS_GIT_COMMIT=
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONPATH=/app \
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
    SVROBS_VAR_DIR=/var/lib/svrobs SVROBS_GIT_COMMIT=${SVROBS_GIT_COMMIT}
WORKDIR /app
# The build context is what .dockerignore lets through: pyproject.toml, alembic.ini,
# migrations/ and every package pyproject's packages.find includes.
COPY . ./
RUN pip install .
# The services run as svrobs: /app is read-only to them; the state folder
# (SVROBS_VAR_DIR: the web session secret, beat's schedule file) is theirs.
RUN useradd --create-home svrobs && mkdir -p /var/lib/svrobs && chown svrobs /var/lib/svrobs
USER svrobs
EXPOSE 8000
CMD ["uvicorn", "service.app:app", "--host", "0.0.0.0", "--port", "8000", \
     "--http", "service.http.request_deadlines:RequestDeadlineProtocol"]
