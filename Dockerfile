# crestscan: multi-stage build, small non-root runtime image running the HTTP service.
# No Docker engine runs on the development machines; this file follows the build steps in CONTRIBUTING.md
# (cargo build --release --locked) and is kept consistent with them by review, not by a CI build.

FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY data ./data
COPY migrations ./migrations
COPY migrations-pg ./migrations-pg
COPY openapi ./openapi
# The learned models are compiled into the binary; ONNX Runtime comes from its PyPI wheel.
COPY models ./models
COPY scripts/setup-onnxruntime ./scripts/setup-onnxruntime
RUN apt-get update -qq && apt-get install -y -qq --no-install-recommends python3-pip >/dev/null \
    && scripts/setup-onnxruntime /src/onnxruntime
# Stripped: the image carries no symbol tables (panics still name their message and location).
RUN CARGO_PROFILE_RELEASE_STRIP=symbols cargo build --release --locked --bin crestscan

FROM debian:bookworm-slim
# Webhooks over HTTPS verify their receivers against the system's roots: add a plant's own CA with
# a layer that copies it to /usr/local/share/ca-certificates/ and runs update-ca-certificates.
RUN apt-get update -qq && apt-get install -y -qq --no-install-recommends ca-certificates >/dev/null \
    && rm -rf /var/lib/apt/lists/*
RUN useradd --system --uid 10001 --home-dir /var/lib/crestscan --create-home crestscan
COPY --from=build /src/target/release/crestscan /usr/local/bin/crestscan
# Found beside the binary (docs/models.md); installed models go in /var/lib/crestscan/models.
COPY --from=build /src/onnxruntime/libonnxruntime.so /usr/local/bin/libonnxruntime.so
USER crestscan
WORKDIR /var/lib/crestscan
# SQLite database, uploaded bundles and temporaries. The API browser (/docs) and the OpenAPI
# document are compiled into the binary: nothing is fetched at run time.
VOLUME ["/var/lib/crestscan"]
# Clients that reach the container by a DNS name (crestscan.plant.local, a compose service name)
# need it listed, or get 421: -e CRESTSCAN_ALLOWED_HOSTS=crestscan.plant.local,crestscan
# The shutdown grace fits inside Docker's default stop timeout (10 s, then SIGKILL); to give
# running jobs longer, raise both together: docker run --stop-timeout 40 -e
# CRESTSCAN_SHUTDOWN_GRACE_SECONDS=30 (compose: stop_grace_period). A killed job is not lost: its
# lease expires and another claim runs it again.
# Listening on every interface, so API keys are required (the service refuses to start otherwise).
# The first key, from the data volume (printed alone on its last line):
#   docker run --rm -v crestscan-data:/var/lib/crestscan crestscan keys create --name root --scopes admin
ENV CRESTSCAN_BIND=0.0.0.0:8080 \
    CRESTSCAN_AUTH=required \
    CRESTSCAN_DATA_DIR=/var/lib/crestscan \
    CRESTSCAN_SHUTDOWN_GRACE_SECONDS=8 \
    CRESTSCAN_LOG_FORMAT=json
EXPOSE 8080
HEALTHCHECK --interval=15s --timeout=5s --start-period=10s --retries=3 CMD ["crestscan", "healthcheck"]
# SIGTERM drains: no new claims, running jobs get the grace period (CRESTSCAN_SHUTDOWN_GRACE_SECONDS).
STOPSIGNAL SIGTERM
ENTRYPOINT ["crestscan"]
CMD ["serve"]
#   docker build -t crestscan .
#   docker run -p 8080:8080 -v crestscan-data:/var/lib/crestscan crestscan
#   docker run --rm crestscan simulate --list
