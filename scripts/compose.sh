#!/usr/bin/env bash
# A compose fleet of robots on this host (compose/compose.yaml, project "sdfr"):
#   scripts/compose.sh up [N]    N robots (default 3), the image built first by `make image`
#   scripts/compose.sh recreate [N]   re-create the N robots' containers (state volumes kept)
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
recreate)
    "${dc[@]}" up -d --force-recreate --scale robot="${2:-3}"
    ;;
down)
    # The robots' state volumes are anonymous; a container re-created by compose keeps its
    # predecessor's, which `down --volumes` (docker-compose 1.29) then misses: remove every
    # anonymous volume the project's containers use.  Named volumes stay unless asked for.
    vols=$(docker ps -aq --filter "label=com.docker.compose.project=$PROJECT" \
        | xargs -r docker inspect -f '{{range .Mounts}}{{if eq .Type "volume"}}{{.Name}} {{end}}{{end}}' \
        | tr ' ' '\n' | grep -E '^[0-9a-f]{64}$' || true)
    down=(down --remove-orphans --timeout 15)
    if [ "${SDFR_COMPOSE_VOLUMES:-0}" = 1 ]; then down+=(--volumes); fi
    "${dc[@]}" "${down[@]}"
    if [ -n "$vols" ]; then
        # shellcheck disable=SC2086
        docker volume rm $vols >/dev/null
    fi
    ;;
*)
    "${dc[@]}" "$@"
    ;;
esac
