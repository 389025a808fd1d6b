# What docker/Dockerfile needs of its base (`python` and `pip` on PATH, Debian's apt), built on a
# Debian imported from a debootstrapped folder, for machines that cannot pull python:3.11-slim.
ARG DEBIAN_IMAGE=swarmvo-offline/debian:bookworm
FROM ${DEBIAN_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /opt/python
ENV PATH=/opt/python/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
