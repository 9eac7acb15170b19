# crestscan: multi-stage build, small non-root runtime image.
# No Docker engine runs on the development machines; this file follows the README's build steps
# (cargo build --release --locked) and is kept consistent with them by review, not by a CI build.

FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY data ./data
COPY migrations ./migrations
COPY openapi ./openapi
RUN cargo build --release --locked --bin crestscan

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --home-dir /var/lib/crestscan --create-home crestscan
COPY --from=build /src/target/release/crestscan /usr/local/bin/crestscan
USER crestscan
WORKDIR /var/lib/crestscan
VOLUME ["/var/lib/crestscan"]
# The HTTP service (`crestscan serve`, its health check and port) arrives with the service issue;
# until then the image runs the command-line tools, e.g.
#   docker run --rm -v "$PWD/out:/var/lib/crestscan" IMAGE simulate --preset ci --out ci
ENTRYPOINT ["crestscan"]
CMD ["--help"]
