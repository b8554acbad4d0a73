"""The API's routes, one module per concern, each with a ``reads`` router (open to anyone who can reach the
server) and, where it changes something, a ``commands`` router (``server.app`` includes it behind the token).

Routes are thin adapters over ``server.service.LabService``: they call it and shape the answer. What went
wrong becomes an HTTP status through one table (``server.errors``), never by a route's own choice. Blocking
service calls are plain ``def`` routes, which FastAPI runs in its thread pool, so the event loop (and the live
websockets) never waits for a shot. A new route goes into the module of its concern (copy a route there);
a new concern is a new module here, included in ``server.app.create_app``.
"""
