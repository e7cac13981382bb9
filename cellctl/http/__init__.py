"""The HTTP front end: `api` (the FastAPI app over the service), `contract` (what every endpoint shares: bodies,
errors, methods), `operator_api` (the web operator's requests), `metrics` (Prometheus), `overlay` (what the
console draws over a camera's frame). It translates; the service decides."""
