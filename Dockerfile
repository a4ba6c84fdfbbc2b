# The `cloudlight` image: built with the toolchain this project is built with, run on a slim
# Debian with the runtime packages that scripts/setup.sh lists (one list, not two).
#
#   docker build -t cloudlight .
#   docker run --rm cloudlight validate /usr/share/cloudlight/examples/topologies/photons-cloud.toml
#
# The entry point is `cloudlight`; a node of a topology runs as
#   docker run --rm -e CLOUDLIGHT_SECRET=... -p 7200:7200/udp -p 9100:9100 cloudlight \
#     node /topology.toml --node cloud --bind 0.0.0.0:7200 --metrics-listen 0.0.0.0:9100
ARG RUST_VERSION=1.95
ARG DEBIAN=bookworm

FROM rust:${RUST_VERSION}-slim-${DEBIAN} AS build
WORKDIR /src
COPY scripts/setup.sh scripts/setup.sh
RUN scripts/setup.sh build
COPY . .
RUN cargo build --release --locked --bin cloudlight \
    && install -D target/release/cloudlight /out/cloudlight

FROM debian:${DEBIAN}-slim
COPY scripts/setup.sh /usr/share/cloudlight/setup.sh
RUN /usr/share/cloudlight/setup.sh runtime && rm -rf /var/lib/apt/lists/*
COPY --from=build /out/cloudlight /usr/local/bin/cloudlight
COPY examples /usr/share/cloudlight/examples
# Not root; HOME holds the reference cache.
RUN useradd --system --create-home --uid 10001 cloudlight
USER cloudlight
WORKDIR /home/cloudlight
ENTRYPOINT ["cloudlight"]
CMD ["--help"]
