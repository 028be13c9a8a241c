# shellcheck shell=bash
# Sourced by deploy/standin-base, deploy/test-image and deploy/test-systemd: podman as it
# runs on this kind of machine, set for this process only (CONTAINERS_CONF), never for the
# whole host and never in the Dockerfile users build.
#
# - runc, not crun: crun fails here (cgroups in hybrid mode); runc works.
# - ulimits no higher than the sandbox's: podman asks for nofile 1048576 and the host's
#   nproc by default, and a sandbox that caps them (nofile 20000 here) refuses the
#   container ("error setting rlimit type 7: operation not permitted").
# Each limit is the lower of this shell's hard limit and a generous default.
# A folder of this process's own (scripts running at once must not share it): the caller
# removes "$podman_conf_dir" when it ends.
podman_conf_dir=$(mktemp -d)
podman_nofile=$(ulimit -Hn)
[ "$podman_nofile" = unlimited ] || [ "$podman_nofile" -gt 65536 ] && podman_nofile=65536
podman_nproc=4096
cat >"$podman_conf_dir/containers.conf" <<CONF
[containers]
default_ulimits = ["nofile=$podman_nofile:$podman_nofile", "nproc=$podman_nproc:$podman_nproc"]
[engine]
runtime = "runc"
CONF
export CONTAINERS_CONF="$podman_conf_dir/containers.conf"
