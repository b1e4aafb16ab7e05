"""The TACF Zenoh tracking service: `tacf serve`.

Modules, one concept each:
    config      Zenoh configs of the service and of its worker processes, from the command line
    cli         `tacf serve`'s arguments, turned into ServiceOptions for serve()
    app         TrackingService: opens the session, wires everything, clean shutdown; serve() for the CLI
    control     the control queryable tacf/<node>/control/<op>: decode, dispatch, reply / reply_err
    manager     SessionManager: the session table, limits, worker supervision and restarts
    pool        WorkerPool: starts worker processes, keeps the warm spares, kills and replaces the hung ones
    frames      FrameHistory: the last few frames of each image key, for init on the frame a box was drawn on
    worker      the worker process: its own Zenoh session, latest-only frames, the tracker, box and health
    outbox      Outbox: the messages to one worker, written to its pipe by a thread of its own
    warm        what the workers' fork server imports once (numpy, OpenCV, the tracker's compiled loops)
    health      HealthStats: counters and timing windows behind the Health message
    state       StateStore: the session table persisted atomically as JSON
    trackers    tracker factories (TACF by profile), passed to workers as "module:function"
    errors      ServiceError(code, message) -> reply_err(Error)
    probe       a minimal control caller (tests); the full client API is tacf_clients
    loopback    loopback peer configs, a frame publisher, a result collector (tests)
    scene       a synthetic moving-target video (tests)

Frames never pass through the service process on their way to a tracker: each worker is a Zenoh client of
the service's endpoint and subscribes to its image key itself. The service process only keeps a short
history of each followed key (to initialise on the frame a box was drawn on) and supervises the workers.
The service benchmark drives it from outside, as a client would: `tacf bench service` (tacf_clients.bench).
"""
