# What docker/Dockerfile needs of its base (`python` and `pip` on PATH, Debian's apt), built on a
# Debian imported from a debootstrapped folder, for machines that cannot pull python:3.11-slim.
# ca-certificates/: the build host's own certificate authorities (a proxy that inspects TLS
# on the way to PyPI), trusted by pip too.
ARG DEBIAN_IMAGE=swarmvo-offline/debian:bookworm
FROM ${DEBIAN_IMAGE}
COPY ca-certificates/ /usr/local/share/ca-certificates/
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && update-ca-certificates \
    && python3 -m venv /opt/python
ENV PATH=/opt/python/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PIP_CERT=/etc/ssl/certs/ca-certificates.crt
