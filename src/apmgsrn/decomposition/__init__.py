"""Domain decomposition (docs/method.md §6): one model per brick of a large volume.

``planner`` cuts a volume into bricks (pure), ``brick_training`` trains one brick where a job runs
(reading only its box), ``executor`` runs the jobs on Dask (local cluster or a user's) or in-process,
``coordinator`` plans, queues, follows and records a run, ``bricked_field`` routes points to the bricks'
networks, and ``brick_model`` reads and writes the model folder. Nothing here is imported by
``import apmgsrn``, and Dask only when a Dask job queue is opened.
"""
