# Stand-in for nginx:1.27-alpine (docker/compose.yaml mounts its nginx.conf over this one).
ARG DEBIAN_IMAGE=swarmvo-offline/debian:bookworm
FROM ${DEBIAN_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends nginx \
    && rm -rf /var/lib/apt/lists/*
CMD ["nginx", "-g", "daemon off;"]
