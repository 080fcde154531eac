#!/usr/bin/env bash
# A compose fleet of robots on this host (compose/compose.yaml, project "sdfr"):
#   scripts/compose.sh up [N]    N robots (default 3), the image built first by `make image`
#   scripts/compose.sh down      remove them, their network and their (anonymous) volumes
#   scripts/compose.sh ARGS...   anything else goes to docker compose / docker-compose
# Named volumes are removed only with SDFR_COMPOSE_VOLUMES=1 (compose.yaml declares none).
set -euo pipefail
cd "$(dirname "$0")/.."
PROJECT=${SDFR_COMPOSE_PROJECT:-sdfr}
if docker compose version >/dev/null 2>&1; then
    dc=(docker compose)
else
    dc=(docker-compose)
fi
dc+=(-f compose/compose.yaml -p "$PROJECT")
case "${1:-}" in
up)
    "${dc[@]}" up -d --scale robot="${2:-3}"
    ;;
down)
    "${dc[@]}" down --volumes --remove-orphans --timeout 15
    ;;
*)
    "${dc[@]}" "$@"
    ;;
esac
