"""Live parameter tuning (issue 28): the current run's parameters, sets and their change log.

``service.ParamsService`` is a run observer made in server/app.py; the routes
(server/http/params.py), the CLI (``xrf param``) and the ROS 2 bridge reach it through the API.
The loop's side and the shared layout are rt_core's xrf/params.h (``channels.params``).
"""
