"""Run folders: the one owner of what ``cerpe run`` and ``cerpe online`` write and everything reads.

The layout (:mod:`~cerpe.runfolder.layout`)::

    RUNDIR/run.json                         method, config, fingerprint, versions, seed, git rev
    RUNDIR/run.lock                         held (flock) by the process writing the folder
    RUNDIR/<encounter>/steps.csv            one row per ordered pair and step
    RUNDIR/<encounter>/robots.csv           one row per robot and step
    RUNDIR/<encounter>/poses/<i>__<j>.tum   estimate of T_cj_ci (TUM: stamp tx ty tz qx qy qz qw)
    RUNDIR/<encounter>/poses/<i>__<j>.gt.tum
    RUNDIR/<encounter>/poses/<i>__<j>.cov   its 6x6 covariance per stamp (cerpe-graph only; ROS order)
    RUNDIR/<encounter>/odometry/<robot>.tum X_i^t (cerpe methods only)
    RUNDIR/<encounter>/DONE.json            written last; presence = encounter finished

Modules, one job each: :mod:`~cerpe.runfolder.write` (open a folder: create or validate run.json
under the lock; an encounter's files), :mod:`~cerpe.runfolder.read` (:class:`~cerpe.runfolder.read.Run`,
:func:`~cerpe.runfolder.read.load_run`), :mod:`~cerpe.runfolder.current` (is a cached run current),
:mod:`~cerpe.runfolder.lock` (one writer per folder), :mod:`~cerpe.runfolder.team` (an online team's
folders as one run), :mod:`~cerpe.runfolder.provenance` (fingerprint, code hash, versions).
"""
