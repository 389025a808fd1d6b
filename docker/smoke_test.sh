#!/usr/bin/env bash
# docker/compose.yaml for real: build the image, `up --scale swarmvo=3` with the balancer and
# PostgreSQL, stream robots through the balancer, kill a replica mid-stream and check that every
# frame is answered once (benchmarks/compose_check.py); the fleet is removed at the end.
#   docker/smoke_test.sh [REPORT_JSON]
# SWARMVO_OFFLINE=1: build the base images locally first (docker/offline/build_images.sh; no
# Docker Hub). PYTHON: the interpreter with the project installed (default .venv/bin/python).
# COMPOSE: the compose command (default `docker compose`, else `docker-compose`).
set -euo pipefail
cd "$(dirname "$0")/.."
report="${1:-/tmp/swarmvo-compose-check.json}"
python="${PYTHON:-.venv/bin/python}"
project=swarmvo-smoke
if [ -z "${COMPOSE:-}" ]; then
    if docker compose version >/dev/null 2>&1; then COMPOSE="docker compose"; else COMPOSE=docker-compose; fi
fi
compose=($COMPOSE -p "$project" -f docker/compose.yaml)
export SWARMVO_API_KEYS="${SWARMVO_API_KEYS:-smoke-$(head -c 12 /dev/urandom | od -An -tx1 | tr -d ' \n')}"
key="${SWARMVO_API_KEYS%%,*}"

if [ "${SWARMVO_OFFLINE:-0}" = 1 ]; then
    docker/offline/build_images.sh
    export SWARMVO_BASE_IMAGE=swarmvo-offline/python:3.11
    export SWARMVO_NGINX_IMAGE=swarmvo-offline/nginx
    export SWARMVO_POSTGRES_IMAGE=swarmvo-offline/postgres
fi
build_start=$(date +%s)
docker build --network host --build-arg "BASE_IMAGE=${SWARMVO_BASE_IMAGE:-python:3.11-slim}" \
    -t "${SWARMVO_IMAGE:-swarmvo}" -f docker/Dockerfile .
echo "image built in $(( $(date +%s) - build_start )) s"

trap '"${compose[@]}" down -v --remove-orphans >/dev/null 2>&1 || true' EXIT
up_start=$(date +%s)
"${compose[@]}" up -d --no-build --scale swarmvo=3
for _ in $(seq 600); do
    curl -fsS http://127.0.0.1:8000/healthz >/dev/null 2>&1 && break
    sleep 1
done
curl -fsS http://127.0.0.1:8000/healthz >/dev/null
echo "fleet answering through the balancer $(( $(date +%s) - up_start )) s after up"
"${compose[@]}" ps
"$python" benchmarks/compose_check.py --project "$project" --key "$key" --out "$report"
