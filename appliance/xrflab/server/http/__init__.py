"""HTTP routes: the appliance's REST API, one module per resource. Only app.py imports these."""
