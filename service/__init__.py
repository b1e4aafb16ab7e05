"""The TACF Zenoh tracking service: `tacf serve`.

Modules, one concept each:
    config      Zenoh configs of the service and of its worker processes, from the command line
    app         TrackingService: opens the session, wires everything, clean shutdown; serve() for the CLI
    control     the control queryable tacf/<node>/control/<op>: decode, dispatch, reply / reply_err
    manager     SessionManager: the session table, limits, worker supervision and restarts
    frames      FrameHistory: the last few frames of each image key, for init on the frame a box was drawn on
    worker      the worker process: its own Zenoh session, latest-only frames, the tracker, box and health
    health      HealthStats: counters and timing windows behind the Health message
    state       StateStore: the session table persisted atomically as JSON
    trackers    tracker factories (TACF by profile)
    bench       a latency / memory benchmark of a running service
"""
