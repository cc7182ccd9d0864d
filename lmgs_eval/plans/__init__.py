"""Benchmark plans as data: a TOML plan, its runs, and the executors that run them (serial, Ray).

``load_plan(path)`` reads and checks a plan (:mod:`.schema`); ``expand(plan)`` lists its runs
(:mod:`.runs`); ``run_plan(plan, executor, results)`` skips the runs the store holds, executes the
others and writes their records (:mod:`.driver`); ``make_executor("serial" | "ray")`` picks where
(:mod:`.executors`). See ``design.md`` beside this file.
"""

from lmgs_eval.plans.driver import Summary, run_plan
from lmgs_eval.plans.executors import EXECUTORS, check_executor, make_executor
from lmgs_eval.plans.runs import Run, expand
from lmgs_eval.plans.schema import Plan, Stage, load_plan, plan_from_dict

__all__ = ["EXECUTORS", "Plan", "Run", "Stage", "Summary", "check_executor", "expand", "load_plan", "make_executor",
           "plan_from_dict", "run_plan"]
