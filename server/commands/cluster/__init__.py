"""``fedhpg-cluster`` (:mod:`.main`): the units it places (:mod:`.units`) and the cluster
engines it places them on (:mod:`.engines`: submitit's SLURM and local; :mod:`.ray_engine`:
Ray, imported only for ``cluster=ray``).
"""
