# The gateway as a container image (deploy/README.md says how to run it).
#
#   docker build -t rs485-gateway .
#   docker run -d --name rs485-gateway \
#     --device /dev/serial/by-id/usb-FTDI_…:/dev/serial/by-id/usb-FTDI_… --group-add dialout \
#     -v "$PWD/gateway.yaml:/etc/gateway/gateway.yaml:ro" \
#     -v rs485-gateway-state:/var/lib/gateway \
#     -e GATEWAY_MQTT__PASSWORD -p 9108:9108 rs485-gateway
#
# Stage one builds the gateway's wheel and the wheels of its dependencies; stage two
# installs them from there, without an index, into a slim runtime that has no compiler,
# no build tools and no wheels left behind. The base is pinned to a Python release.
# RUN --mount needs BuildKit: the default builder since Docker 23, and in podman/buildah.
ARG PYTHON_IMAGE=python:3.11.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
WORKDIR /src
# Only what the wheel is built from: a change elsewhere does not rebuild it.
COPY pyproject.toml README.md ./
COPY gateway ./gateway
RUN pip wheel --no-cache-dir --disable-pip-version-check --wheel-dir /wheels . \
    && sha256sum /wheels/*.whl >/wheels.sha256

FROM ${PYTHON_IMAGE}
# Fixed ids, so that a bind-mounted state directory can be chowned on the host
# (chown 10001:10001 DIR). dialout (gid 20 in Debian) owns /dev/ttyUSB* and /dev/ttyACM*
# on Debian, Ubuntu and Raspberry Pi OS hosts; elsewhere add the device's group by number
# (--group-add "$(stat -L -c %g /dev/serial/by-id/usb-…)").
RUN groupadd --system --gid 10001 gateway \
    && useradd --system --uid 10001 --gid gateway --groups dialout \
        --home-dir /var/lib/gateway --no-create-home --shell /usr/sbin/nologin gateway \
    && install -d -o gateway -g gateway -m 0700 /var/lib/gateway \
    && install -d -m 0755 /etc/gateway
# The wheels' checksums first, as a file (it lists what is installed): a new wheel then
# rebuilds the install below. Buildah (podman build) leaves a bind mount from another
# stage out of its cache key (containers/buildah#6609) and would keep the old gateway.
COPY --from=build /wheels.sha256 /usr/local/share/rs485-gateway/wheels.sha256
# The wheels are mounted for this step only, so they never become a layer of the image.
RUN --mount=type=bind,from=build,source=/wheels,target=/wheels \
    pip install --no-cache-dir --disable-pip-version-check --no-index --find-links=/wheels \
        /wheels/rs485_sensor_gateway-*.whl

# The gateway keeps its MQTT queue in $STATE_DIRECTORY when the config sets no state_dir.
# GATEWAY_* variables win over the config file: JSON log lines suit `docker logs` and log
# collectors; -e GATEWAY_LOGGING__FORMAT=text for reading them by eye.
ENV STATE_DIRECTORY=/var/lib/gateway \
    GATEWAY_LOGGING__FORMAT=json \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1
VOLUME ["/var/lib/gateway"]
WORKDIR /var/lib/gateway
# The user "gateway" by its id (Kubernetes' runAsNonRoot can only check a number), without
# ":group": the runtime then applies its memberships in /etc/group (dialout); with a group
# given it would apply that group only.
USER 10001

# /metrics and /healthz (prometheus.port in the config; the check below assumes 9108).
EXPOSE 9108
# /healthz answers 503 while a port is closed or MQTT is down with a full queue; urlopen
# raises on that (and on no answer), so the check fails. Slim images have no curl.
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:9108/healthz', timeout=4)"]

# The config is mounted here (read-only); any other sub-command works too:
# docker run --rm rs485-gateway profiles
ENTRYPOINT ["gateway"]
CMD ["run", "--config", "/etc/gateway/gateway.yaml"]
