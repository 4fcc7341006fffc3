# Mirrors `make run`: Python 3.11, the package installed into a venv, `scandiff serve`.
FROM python:3.11-slim

WORKDIR /srv/scandiff
RUN apt-get update && apt-get install -y --no-install-recommends make \
    && rm -rf /var/lib/apt/lists/*

COPY pyproject.toml README.md Makefile alembic.ini ./
COPY app ./app
COPY migrations ./migrations
COPY static ./static
RUN make install

ENV SCANDIFF_DATA_DIR=/var/lib/scandiff \
    SCANDIFF_HOST=0.0.0.0 \
    SCANDIFF_PORT=8000
VOLUME /var/lib/scandiff
EXPOSE 8000
CMD [".venv/bin/scandiff", "serve"]
