"""The XRF Lab appliance: FastAPI app, run supervisor, WebSocket hub (see app.create_app)."""
