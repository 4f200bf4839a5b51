#!/bin/sh
# Start MDS-Ach node by node with plain processes: no launch file, no `mds-ach start`.
# Each line is what `ros2 run mds_ach <node>` executes (`mds-ach-<node>` in a venv's bin/), so copy,
# reorder or drop nodes as you like (every node also starts alone, in any order). Pid files and logs go
# where `mds-ach status` and `mds-ach stop` (and scripts/stop_nodes.sh) look for them.
#
# Usage: scripts/start_nodes.sh [--nocan]      --nocan: simulated MDS bus instead of CAN
# Environment: MDS_ACH_RUNTIME_DIR  pid/log directory (default $XDG_RUNTIME_DIR/mds-ach, else /tmp/mds-ach-UID)
#              MDS_ACH_BIN          directory holding the node executables: a bin/ (mds-ach-daemon, ...) or an
#                                   ament lib/mds_ach/ (daemon, ...) (default: found automatically)
#              MDS_ACH_ROBOT        robot variant (default: the one saved by `mds-ach changerobot`)
set -eu

case "${1:-}" in
    --nocan|nocan) nocan=--nocan ;;
    "") nocan= ;;
    -h|--help) sed -n '2,13p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "usage: $0 [--nocan]" >&2; exit 2 ;;
esac

# The runtime directory, same rule as mds_ach.paths.runtime_dir().
if [ -n "${MDS_ACH_RUNTIME_DIR:-}" ]; then rt=$MDS_ACH_RUNTIME_DIR
elif [ -n "${XDG_RUNTIME_DIR:-}" ]; then rt=$XDG_RUNTIME_DIR/mds-ach
else rt=/tmp/mds-ach-$(id -u)
fi
mkdir -p "$rt"

# Where the executables are: $MDS_ACH_BIN, the checkout's venv, the ament index (colcon install), PATH.
here=$(cd "$(dirname "$0")/.." && pwd)
if [ -n "${MDS_ACH_BIN:-}" ]; then bin=$MDS_ACH_BIN
elif [ -x "$here/.venv/bin/mds-ach" ]; then bin=$here/.venv/bin
elif prefix=$(python3 -c 'from ament_index_python.packages import get_package_prefix as p; print(p("mds_ach"))' \
              2>/dev/null); then bin=$prefix/lib/mds_ach
elif command -v mds-ach >/dev/null; then bin=$(dirname "$(command -v mds-ach)")
else echo "$0: cannot find the mds_ach executables; set MDS_ACH_BIN" >&2; exit 1
fi
# A bin/ directory names them mds-ach-daemon, ...; an ament lib/mds_ach/ (ros2 run) daemon, ...
if [ -x "$bin/mds-ach-daemon" ]; then pfx=mds-ach-; else pfx=; fi

start_node() {  # start_node NAME [ARGS...]: one node in the background, its pid and log in $rt
    name=$1; shift
    "$bin/$pfx$name" "$@" >"$rt/$name.log" 2>&1 </dev/null &
    echo $! >"$rt/$name.pid"
    echo "  $name started (pid $!, log $rt/$name.log)"
}

fail() {
    echo "$0: $1; last lines of $rt/$2.log:" >&2
    tail -n 20 "$rt/$2.log" >&2 || true
    exit 1
}

"$bin/mds-ach" make >/dev/null       # the channels (existing ones are kept)

start_node daemon $nocan
# Wait until the daemon's loop runs: `read --once` exits 0 only when a new state frame arrives.
tries=0
until "$bin/${pfx}read" --once >/dev/null 2>&1; do
    kill -0 "$(cat "$rt/daemon.pid")" 2>/dev/null || fail "the daemon exited" daemon
    tries=$((tries + 1))
    [ "$tries" -lt 60 ] || fail "no state from the daemon after 60 tries" daemon
done

start_node mux
start_node filter
start_node collision
start_node ik
start_node bridge
echo "started; 'mds-ach status' shows them, scripts/stop_nodes.sh stops them"
