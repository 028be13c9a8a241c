# shellcheck shell=bash
# Sourced by deploy/test-image and deploy/test-systemd: how a check script reports.
# Each check prints "ok: …" or "FAIL: …" with its evidence, each phase its time, and
# `report_end NAME` exits 1 if any check failed. `quietly` reads $workdir, which the
# script sets before its first use.

failures=0
ok() { echo "ok: $*"; }
fail() {
    echo "FAIL: $*"
    failures=$((failures + 1))
}

# Milliseconds of the clock (date's %N, not $EPOCHREALTIME, whose decimal point follows
# the locale).
now_ms() { echo $(($(date +%s%N) / 1000000)); }
# Seconds since START_MS (a now_ms), one decimal.
since() {
    local elapsed=$(($(now_ms) - $1))
    printf '%d.%d' $((elapsed / 1000)) $((elapsed % 1000 / 100))
}
started=$(now_ms)
phase_started=$started
# The time since the last call (or the start), printed as "time: WHAT N.N s".
lap() {
    echo "time: $1 $(since "$phase_started") s"
    phase_started=$(now_ms)
}

# Run a command whose output is only worth reading when it fails.
# (Not `if cmd; then ...; fi; status=$?`: after an if without else, $? is 0.)
quietly() {
    local log=${workdir:?set by the script}/quiet.log status=0
    "$@" >"$log" 2>&1 || status=$?
    [ "$status" -eq 0 ] || tail -n 40 "$log"
    return "$status"
}

# Wait until CONDITION (a command) succeeds, for at most SECONDS; false if it never did.
wait_for() {
    local seconds=$1
    shift
    local deadline=$((SECONDS + seconds))
    until "$@"; do
        [ "$SECONDS" -lt "$deadline" ] || return 1
        sleep 0.5
    done
}

# The total time, then exit: 1 if any check failed.
report_end() {
    phase_started=$started
    lap total
    if [ "$failures" -gt 0 ]; then
        echo "$1: $failures check(s) failed"
        exit 1
    fi
    echo "$1: every check passed"
}
