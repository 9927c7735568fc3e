# otofit service image. Build: docker build -t otofit .
# Run:   docker run -p 127.0.0.1:8080:8080 -v otofit-data:/var/lib/otofit otofit
# One image, two roles: the default command is `serve` (SQLite in the volume, jobs run
# in-process); with PostgreSQL (OTOFIT_DATABASE=postgres://…) run any number of
# `otofit serve --workers 0` and `otofit worker --data-dir /var/lib/otofit` containers
# on a shared volume: deploy/compose.yaml, docs/deploy.md.
# Release profile here only (CI and tests use the optimised dev profile).
FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY crates ./crates
COPY migrations ./migrations
COPY models ./models
COPY reference ./reference
COPY openapi.yaml ./
RUN cargo build --release --locked --bin otofit

FROM debian:bookworm-slim
RUN useradd --system --home /var/lib/otofit otofit && mkdir -p /var/lib/otofit && chown otofit /var/lib/otofit
COPY --from=build /src/target/release/otofit /usr/local/bin/otofit
COPY --from=build /src/models /usr/share/otofit/models
COPY --from=build /src/reference /usr/share/otofit/reference
USER otofit
WORKDIR /usr/share/otofit
VOLUME /var/lib/otofit
EXPOSE 8080
# Inside a container the service must listen beyond loopback; publish the port with care.
CMD ["otofit", "serve", "--addr", "0.0.0.0:8080", "--data-dir", "/var/lib/otofit", "--default-model", "/usr/share/otofit/models/default.otofit"]
