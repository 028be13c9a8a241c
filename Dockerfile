# The gateway as a container: a wheel built in one stage, installed in a slim runtime.
# The runtime runs as a non-root user in the dialout group so it can open /dev/ttyUSB*.
# HEALTHCHECK on /healthz and the documented config mount come with the service issues.
FROM python:3.11.11-slim-bookworm AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY gateway ./gateway
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM python:3.11.11-slim-bookworm
RUN useradd --system --no-create-home --groups dialout gateway
COPY --from=build /wheels /wheels
RUN pip install --no-cache-dir /wheels/*.whl && rm -rf /wheels
USER gateway
ENTRYPOINT ["gateway"]
CMD ["profiles"]
