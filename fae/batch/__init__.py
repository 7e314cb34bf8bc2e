"""Many videos at once: `fae batch` renders a list of jobs on a Dask cluster.

    fae.batch.jobs      the job list: a CSV or JSON file, or a glob of .fap files x heads
    fae.batch.manifest  what a run did, per job, and which outputs a rerun may keep
    fae.batch.worker    one job on a worker: the head's Player and renderer kept between jobs
    fae.batch.run       the Dask side: an embedded LocalCluster or a given scheduler,
                        retries, progress, atomic outputs

Jobs carry their inputs' bytes to the workers and bring the video's bytes back, so the
workers need fae installed but no shared folder; nothing of Dask runs per frame.
"""
