# Stand-in for postgres:16-alpine: Debian's PostgreSQL, the same POSTGRES_USER / POSTGRES_PASSWORD /
# POSTGRES_DB variables and data folder, pg_isready for the health check.
ARG DEBIAN_IMAGE=swarmvo-offline/debian:bookworm
FROM ${DEBIAN_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends postgresql \
    && rm -rf /var/lib/apt/lists/*
COPY postgres-entrypoint.sh /usr/local/bin/postgres-entrypoint.sh
ENV PGDATA=/var/lib/postgresql/data
CMD ["sh", "/usr/local/bin/postgres-entrypoint.sh"]
