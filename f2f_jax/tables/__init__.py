"""The paper's evaluation tables for any set of finger designers (what ``experiments/evaluate.py``
prints).  Not to be confused with ``sim.evaluate``, the simulator call the tables are made of.

    designers = {"WSG50": wsg50_designer(cfg), "Imprint": imprint_designer(cfg)}
    t1 = table1(designers, objects, cfg)          # grasp, S1..S4, S avg, R-30..R+30, R avg
    t2 = table2(designers, objects, cfg)          # grasp success under the paper's perturbations
    t1.write("runs/eval", "table1")               # table1.md (ours beside the paper), .csv, .png

``paper``: the paper's figures and Table 2's conditions; ``designers``: the rows as callables;
``table``: Tables 1 and 2 simulated and written; ``stats``: fitness ranking, neighbourhoods, gains;
``seeds``: the tables of several runs (seeds) as mean ± sd, each row against a reference row;
``rows``: the rows and objects an evaluation of a run scores (``experiments/evaluate.py`` and the
studies in ``research/``).
"""

from f2f_jax.tables.designers import (
    Design,
    Designer,
    imprint_designer,
    make_designs,
    nets_designer,
    objects_array,
    pair_designer,
    random_embedding_designer,
    wsg50_designer,
    wsg_fmf_designer,
)
from f2f_jax.tables.paper import (
    OBJECTIVE_ROWS,
    PAPER_OBJECTS,
    PAPER_TABLE1,
    PAPER_TABLE2,
    ROBUSTNESS,
    STABILITY,
    TABLE1_COLUMNS,
    TABLE2_COLUMNS,
    TABLE2_CONDITIONS,
    Condition,
)
from f2f_jax.tables.seeds import SeedTable, combine_results, load_results, merge_results
from f2f_jax.tables.stats import (
    candidate_designs,
    candidate_outcomes,
    fitness_ranking,
    nearest_own_scores,
    neighbourhood_stats,
    paired_gain,
    paired_spearman,
    ranking_report,
    ranking_stats,
    within_object_spearman,
)
from f2f_jax.tables.table import Table, position_offsets, prepare_objects, table1, table1_values, table2

__all__ = [
    "OBJECTIVE_ROWS", "PAPER_OBJECTS", "PAPER_TABLE1", "PAPER_TABLE2", "ROBUSTNESS", "STABILITY",
    "TABLE1_COLUMNS", "TABLE2_COLUMNS", "TABLE2_CONDITIONS", "Condition", "Design", "Designer",
    "SeedTable", "Table", "candidate_designs", "candidate_outcomes", "combine_results", "fitness_ranking",
    "imprint_designer", "load_results", "make_designs", "merge_results", "nearest_own_scores",
    "neighbourhood_stats", "nets_designer",
    "objects_array", "pair_designer", "paired_gain", "paired_spearman", "position_offsets", "prepare_objects",
    "random_embedding_designer", "ranking_report", "ranking_stats", "table1", "table1_values", "table2", "wsg50_designer",
    "within_object_spearman", "wsg_fmf_designer",
]
