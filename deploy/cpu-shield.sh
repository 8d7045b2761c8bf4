#!/usr/bin/env bash
# CPU isolation without a reboot: a cpuset "shield" (as `cset shield` makes one). Every task
# that can move goes to the housekeeping CPUs; the shielded CPU runs only what is started with
# `run`. Kernel threads bound to the shielded CPU stay (only `isolcpus=` at boot removes those).
#
#   sudo deploy/cpu-shield.sh on 1          # shield CPU 1, everything else on the other CPUs
#   sudo deploy/cpu-shield.sh on 2,3        # shield CPUs 2 and 3 (a session's servo + worker)
#   sudo deploy/cpu-shield.sh run 1 CMD...  # run CMD on the shielded CPUs
#   sudo deploy/cpu-shield.sh off           # undo
#
# cgroup v1 cpuset only (mounted at /sys/fs/cgroup/cpuset). On cgroup v2 (most current
# distributions) use systemd instead: `systemctl set-property --runtime U AllowedCPUs=0` for U
# in user.slice, system.slice and init.scope, and `AllowedCPUs=1` in the daemon's unit.
# Measured on a 2-core VM in docs/deploy.md.
set -euo pipefail

ROOT=/sys/fs/cgroup/cpuset
HK="$ROOT/hk_housekeeping"
RT="$ROOT/hk_shield"

die() { echo "cpu-shield: $*" >&2; exit 1; }
[[ -f "$ROOT/cpuset.cpus" ]] || die "no cgroup v1 cpuset at $ROOT (cgroup v2: see the comment at the top)"
[[ $(id -u) == 0 ]] || die "needs root"

all_cpus() { cat "$ROOT/cpuset.effective_cpus" 2>/dev/null || cat "$ROOT/cpuset.cpus"; }

# CPUs of the list $1 (e.g. 0-3,6) except those of the comma list $2, as a list.
others() {
    local list=$1 skip=",$2," out=() part a b i
    IFS=, read -ra parts <<< "$list"
    for part in "${parts[@]}"; do
        if [[ $part == *-* ]]; then a=${part%-*}; b=${part#*-}; else a=$part; b=$part; fi
        for ((i = a; i <= b; i++)); do [[ $skip == *",$i,"* ]] || out+=("$i"); done
    done
    local IFS=,; echo "${out[*]}"
}

case "${1:-}" in
on)
    cpu=${2:?usage: cpu-shield.sh on CPU[,CPU...]}
    [[ $cpu =~ ^[0-9]+(,[0-9]+)*$ ]] || die "CPU must be a number or a comma list of numbers"
    hk=$(others "$(all_cpus)" "$cpu")
    [[ -n $hk ]] || die "no CPU left for housekeeping"
    mems=$(cat "$ROOT/cpuset.mems")
    mkdir -p "$HK" "$RT"
    echo "$hk" > "$HK/cpuset.cpus"; echo "$mems" > "$HK/cpuset.mems"
    echo "$cpu" > "$RT/cpuset.cpus"; echo "$mems" > "$RT/cpuset.mems"
    echo 1 > "$RT/cpuset.cpu_exclusive"
    moved=0; stuck=0
    while read -r pid; do
        if echo "$pid" > "$HK/tasks" 2>/dev/null; then moved=$((moved + 1)); else stuck=$((stuck + 1)); fi
    done < "$ROOT/tasks"
    # Separate scheduling domains: the scheduler no longer balances load onto the shield.
    echo 0 > "$ROOT/cpuset.sched_load_balance" || true
    echo "cpu-shield: CPU(s) $cpu shielded; $moved tasks moved to CPUs $hk, $stuck could not move (kernel threads)"
    ;;
run)
    [[ -d $RT ]] || die "no shield: run 'cpu-shield.sh on CPU' first"
    shift 2 || die "usage: cpu-shield.sh run CPU CMD..."
    [[ $# -gt 0 ]] || die "usage: cpu-shield.sh run CPU CMD..."
    echo $$ > "$RT/tasks"
    exec "$@"
    ;;
off)
    for g in "$RT" "$HK"; do
        [[ -d $g ]] || continue
        while read -r pid; do echo "$pid" > "$ROOT/tasks" 2>/dev/null || true; done < "$g/tasks"
        rmdir "$g"
    done
    echo 1 > "$ROOT/cpuset.sched_load_balance" || true
    echo "cpu-shield: off"
    ;;
*)
    die "usage: cpu-shield.sh on CPU[,CPU...] | run CPU CMD... | off"
    ;;
esac
