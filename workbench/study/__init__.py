"""Study framework: declare tasks, run them resumably (local processes or Dask), summarise.

tasks (Study, TaskOutput, TaskContext) -> execute (run_study) -> store (RunStore: manifest,
per-task files, tidy Parquet/CSV tables) -> summary (Rate, Spread) -> report (tables, Claim).
"""

from workbench.study.execute import RunResult, StudyInterrupted, run_study
from workbench.study.report import Claim, fmt_rate, md_table, png_bytes, supported, tasks_phrase
from workbench.study.store import RunStore, TaskError
from workbench.study.summary import Rate, Spread, to_jsonable
from workbench.study.tasks import Study, TaskContext, TaskOutput, seed_sequence
from workbench.study.threads import limit_threads

__all__ = ["Claim", "Rate", "RunResult", "RunStore", "Spread", "Study", "StudyInterrupted",
           "TaskContext", "TaskError", "TaskOutput", "fmt_rate", "limit_threads", "md_table",
           "png_bytes", "run_study", "seed_sequence", "supported", "tasks_phrase", "to_jsonable"]
