#!/usr/bin/env bash
# Build the quadsr image with podman, run the SITL in a container with its HIL port published on 127.0.0.1,
# and fly Case II from the host against it; then run docker/compose.yaml's two services the way compose
# would (one network, the SITL reached by its service name, the companion started once the SITL is healthy,
# results in a volume). Prints every stage; exits non-zero when any stage fails.
#
#   sudo docker/smoke.sh [--clean]       # --clean: also remove the images at the end (default: keep them)
#
# Needs: root, podman with runc, debootstrap (Debian: apt-get install -y podman runc debootstrap), the
# host's quadsr for the flight ($PYTHON -m quadsr.cli; default python3; it also reads compose.yaml with
# PyYAML), and PyPI reachable from the build. No registry is pulled from: the base image is a Debian bookworm
# made with debootstrap (python3.11 + venv) and imported with `podman import`; it is reused on the next run.
# Exit codes: 0 both flights flown; 1 a stage failed; 77 podman or debootstrap missing (nothing was run).
#
# Settings (environment): PYTHON, QUADSR_IMAGE (localhost/quadsr:smoke), QUADSR_BASE_IMAGE
# (localhost/quadsr-base:bookworm), DEBIAN_MIRROR (http://deb.debian.org/debian), QUADSR_SMOKE_PORT
# (host UDP port for the HIL link; default a free one). The host flight is kept in a folder it prints.
set -euo pipefail

for tool in podman debootstrap; do
    if ! command -v "$tool" >/dev/null; then
        echo "smoke: $tool is not installed: apt-get install -y podman runc debootstrap (as root); nothing run"
        exit 77
    fi
done

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PYTHON=${PYTHON:-python3}
IMAGE=${QUADSR_IMAGE:-localhost/quadsr:smoke}
BASE_IMAGE=${QUADSR_BASE_IMAGE:-localhost/quadsr-base:bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
CLEAN=0
[[ "${1:-}" == "--clean" ]] && CLEAN=1
TAG=quadsr-smoke-$$
SITL=$TAG-sitl                 # the SITL flown from the host
SITL2=$TAG-compose-sitl        # compose's services, by their compose names on their own network
COMPANION=$TAG-compose-companion
NETWORK=$TAG-net
VOLUME=$TAG-results
WORK=$(mktemp -d /tmp/quadsr-smoke.XXXXXX)
OUT=$WORK/case2
FLY_PID=

say() { printf '\n== smoke: %s\n' "$*"; }
fail() { printf 'smoke: FAILED: %s\n' "$*" >&2; exit 1; }

cleanup() {
    local rc=$?
    if [[ -n "$FLY_PID" ]] && kill -0 "$FLY_PID" 2>/dev/null; then kill "$FLY_PID" 2>/dev/null || true; fi
    for container in "$SITL" "$SITL2" "$COMPANION"; do
        if podman container exists "$container" 2>/dev/null; then
            if [[ "$rc" != 0 ]]; then
                echo "-- $container log (last 5 lines):"
                podman logs --tail 5 "$container" 2>&1 || true
            fi
            podman rm -f -t 3 "$container" >/dev/null 2>&1 || true
        fi
    done
    podman network exists "$NETWORK" 2>/dev/null && podman network rm -f "$NETWORK" >/dev/null 2>&1
    podman volume exists "$VOLUME" 2>/dev/null && podman volume rm -f "$VOLUME" >/dev/null 2>&1
    if [[ "$CLEAN" == 1 ]]; then podman rmi -f "$IMAGE" "$BASE_IMAGE" >/dev/null 2>&1 || true; fi
    rm -rf "$WORK/rootfs"
    [[ -d "$OUT" ]] || rm -rf "$WORK"  # kept only when it holds the flight
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# Start a container quietly (podman 4.3 without systemd logs harmless errors about health-check timers:
# the checks are run here with `podman healthcheck run`); print podman's messages only if it fails.
start_container() {
    podman run -d "$@" >"$WORK/run.log" 2>&1 || { cat "$WORK/run.log"; fail "podman run $*"; }
}

# Run the image's HEALTHCHECK until it passes (60 s at most); prints its last line.
wait_healthy() {
    local container=$1 result=""
    for _ in $(seq 60); do
        if result=$(podman healthcheck run "$container" 2>&1); then
            echo "podman healthcheck run $container: ${result:-healthy}"
            return 0
        fi
        if [[ $(podman inspect --format '{{.State.Running}}' "$container" 2>/dev/null) != true ]]; then
            fail "$container stopped: $(podman logs "$container" 2>&1 | tail -5)"
        fi
        sleep 1
    done
    fail "the health check of $container never passed: $result"
}

[[ $(id -u) == 0 ]] || fail "run as root (Debian's podman is used rootful here, with runc)"
"$PYTHON" -c "import quadsr.cli, yaml" 2>/dev/null \
    || fail "$PYTHON cannot import quadsr and yaml: set PYTHON to the venv's python"

# Debian's podman on this kind of machine: runc as the runtime, and the container's open-file and process
# ulimits lowered below the host's hard limits (podman's defaults ask for more, which a sandboxed root may not
# grant: "runc create failed: ... error setting rlimit type 6: operation not permitted").
cat >"$WORK/containers.conf" <<'EOF'
[containers]
default_ulimits = ["nofile=1024:4096", "nproc=4096:4096"]

[engine]
runtime = "runc"
EOF
export CONTAINERS_CONF="$WORK/containers.conf"

if podman image exists "$BASE_IMAGE"; then
    say "base image $BASE_IMAGE exists: reused"
else
    say "base image: debootstrap Debian bookworm (python3 + venv) from $MIRROR"
    start=$SECONDS
    debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
        bookworm "$WORK/rootfs" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 \
        || { tail -20 "$WORK/debootstrap.log"; fail "debootstrap (log above)"; }
    rm -rf "$WORK"/rootfs/var/cache/apt/archives/*.deb "$WORK"/rootfs/var/lib/apt/lists/*
    # The host's local CA certificates too: behind a TLS-intercepting proxy (as on our machines) pip in the
    # build must trust what the host trusts. PIP_CERT: pip < 24.2 (the venv's first pip) reads only certifi.
    shopt -s nullglob
    local_cas=(/usr/local/share/ca-certificates/*.crt)
    shopt -u nullglob
    if ((${#local_cas[@]})); then
        cp "${local_cas[@]}" "$WORK/rootfs/usr/local/share/ca-certificates/"
        chroot "$WORK/rootfs" update-ca-certificates >/dev/null 2>&1
        echo "added the host's local CA certificates: ${local_cas[*]}"
    fi
    tar -C "$WORK/rootfs" -c . | podman import --quiet \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
        --change 'CMD ["/bin/bash"]' - "$BASE_IMAGE" >/dev/null
    rm -rf "$WORK/rootfs"
    echo "base image $BASE_IMAGE made in $((SECONDS - start)) s: $(podman run --rm "$BASE_IMAGE" python3 --version)"
fi

say "build $IMAGE from $REPO (docker/Dockerfile, BASE=$BASE_IMAGE)"
start=$SECONDS
# --format docker: the OCI image format has no HEALTHCHECK and podman would drop it.
podman build --format docker --pull=never --build-arg "BASE=$BASE_IMAGE" \
    -f "$REPO/docker/Dockerfile" -t "$IMAGE" "$REPO" >"$WORK/build.log" 2>&1 \
    || { tail -30 "$WORK/build.log"; fail "podman build (log above)"; }
echo "built in $((SECONDS - start)) s: $(podman image inspect --format '{{.Size}}' "$IMAGE" | awk '{printf "%.0f MB", $1/1e6}')"
echo "health check: $(podman image inspect --format '{{.Config.Healthcheck.Test}}' "$IMAGE")"
echo "user: $(podman image inspect --format '{{.Config.User}}' "$IMAGE"); command: $(podman image inspect --format '{{.Config.Cmd}}' "$IMAGE")"

# ---- 1. the SITL in a container, Case II flown from the host ----------------------------------------------
PORT=${QUADSR_SMOKE_PORT:-$("$PYTHON" -c 'import socket; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}
say "run the SITL container (default command), HIL port 4560/udp published on 127.0.0.1:$PORT"
start_container --name "$SITL" -p "127.0.0.1:$PORT:4560/udp" "$IMAGE"
wait_healthy "$SITL"
echo "SITL: $(podman logs "$SITL" 2>&1 | head -1)"
strict=(python /opt/quadsr/healthcheck.py --require stepping)
if before=$(podman exec "$SITL" "${strict[@]}" 2>&1); then
    fail "--require stepping passed before any companion: $before"
fi
echo "before the flight, ${strict[*]}: $before"

say "fly Case II from the host: quadsr fly --hil udp:127.0.0.1:$PORT --out $OUT"
"$PYTHON" -m quadsr.cli model-from-vehicle -o "$WORK/true.yaml"
"$PYTHON" -m quadsr.cli fly --model "$WORK/true.yaml" --trajectory case2 --hil "udp:127.0.0.1:$PORT" \
    --out "$OUT" --no-progress &
FLY_PID=$!
sleep 4
during_rc=0
during=$(podman exec "$SITL" "${strict[@]}" 2>&1) || during_rc=$?
echo "during the flight, ${strict[*]}: $during"
fly_rc=0
wait "$FLY_PID" || fly_rc=$?
FLY_PID=
[[ "$fly_rc" == 0 ]] || fail "quadsr fly exited $fly_rc"
[[ "$during_rc" == 0 ]] || fail "the SITL was not stepping during the flight"
cat "$OUT/metrics.md"
echo "files in $OUT: $(cd "$OUT" && echo *)"
podman rm -f -t 3 "$SITL" >/dev/null 2>&1

# ---- 2. compose.yaml's services, as compose runs them ------------------------------------------------------
say "compose.yaml's services: sitl (by that name on network $NETWORK), companion once sitl is healthy"
mapfile -d '' -t companion_cmd < <("$PYTHON" -c '
import sys, yaml
c = yaml.safe_load(open(sys.argv[1]))
sys.stdout.write("".join(a + "\0" for a in c["services"]["companion"]["command"]))
' "$REPO/docker/compose.yaml")
((${#companion_cmd[@]})) || fail "no companion command in docker/compose.yaml"
podman network create "$NETWORK" >/dev/null
podman volume create "$VOLUME" >/dev/null
start_container --name "$SITL2" --network "$NETWORK" --network-alias sitl "$IMAGE"
wait_healthy "$SITL2"
echo "companion: ${companion_cmd[*]}"
start=$SECONDS
companion_rc=0
# --no-healthcheck: as compose.yaml's `healthcheck: disable: true` (the image's check is the SITL's).
podman run --name "$COMPANION" --no-healthcheck --network "$NETWORK" -v "$VOLUME:/results" "$IMAGE" \
    "${companion_cmd[@]}" || companion_rc=$?
echo "companion exited $companion_rc after $((SECONDS - start)) s"
[[ "$companion_rc" == 0 ]] || fail "the compose companion exited $companion_rc"
echo "the results volume holds: $(podman run --rm --no-healthcheck -v "$VOLUME:/results" "$IMAGE" ls /results/case2 | tr '\n' ' ')"

say "OK: Case II flown from the host against the SITL container, and by compose.yaml's companion container"
