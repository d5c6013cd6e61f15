"""``stepnft compare``'s flags (:class:`CompareCommand`), its help, and the command line that
reproduces a comparison (quoted in its reports)."""

from __future__ import annotations

from dataclasses import dataclass, field

from stepnft.algos.variants import describe_variants, variant_names
from stepnft.names import split_names
from stepnft.settings import EVAL_SEEDS_END, SEED_MAX

JOBS_MAX = 256
"""The most runs ``stepnft compare`` starts at once (one process each)."""


@dataclass
class CompareCommand:
    """Compare RL fine-tuning algorithms and ablations from the same SFT start per seed, on one
    env-step budget: success per task with 95 % CIs, paired differences to the reference, env
    steps, wall-clock and learner speed (OUT/comparison.md, .csv, .png)."""

    config: str = "configs/quickstart.yaml"
    """Base run config (YAML): tasks, envs, demonstrations, policy, SFT, evaluation and the
    shared algorithm settings; each variant changes only its algo.* fields."""
    algos: list[str] = field(default_factory=lambda: ["stepnft", "ppo", "grpo"])
    """Variants to compare (space- or comma-separated), from the list above."""
    seeds: list[int] = field(default_factory=lambda: [0])
    """One SFT policy per seed (demonstrations and initial states seeded by it); every variant
    runs once per seed from it."""
    tasks: list[str] | None = None
    """Sets the base config's env.tasks (space- or comma-separated; None: keep them)."""
    env_steps: int | None = None
    """Sets the base config's env_step_budget: the RL env-step budget of every run (None: keep it)."""
    jobs: int = 0
    """Runs at once, one subprocess each (0: one per CPU core)."""
    out: str = "runs/compare"
    """Comparison folder; rerun the same command on it to resume."""
    reference: str = "stepnft"
    """Variant the paired differences are taken against (if compared; else the first)."""
    eval_episodes: int | None = None
    """Sets the base config's eval.episodes: episodes per task before and after RL (None: keep it)."""
    suites: list[str] = field(default_factory=list)
    """Also evaluate every final policy and every SFT start on these suites (ind, vision,
    semantic, execution; space- or comma-separated): the table of IND / OOD success
    (OUT/suites.md). Empty: no suite evaluation."""
    suite_episodes: int = 50
    """Episodes per task and suite for --suites."""
    variant_set: list[str] = field(default_factory=list)
    """Settings of one compared variant on top of its own, VARIANT.FIELD=VALUE (algo.* fields,
    YAML values; space-separated), e.g. ppo-shaped.lr=3e-5: a setting tuned for one method on
    this config. Recorded in OUT/compare.json; a rerun may change a variant's only while it has
    no run folder (delete OUT/runs/VARIANT to rerun it with new ones)."""

    def __post_init__(self) -> None:
        # --tasks, --env-steps and --eval-episodes are checked by the config sections they set
        # (stepnft.compare.plan.comparison_config); the rest is the comparison's own.
        self.algos = list(dict.fromkeys(split_names(self.algos)))
        self.tasks = split_names(self.tasks) or None
        self.suites = split_names(self.suites)
        known = variant_names()
        unknown = [a for a in self.algos if a not in known]
        if not self.algos or unknown:
            raise ValueError(f"--algos {','.join(unknown) or '(none)'}: choose from {', '.join(known)}")
        if self.reference not in known:
            raise ValueError(f"--reference must be one of {', '.join(known)}, got {self.reference!r}")
        for flag, path in (("--config", self.config), ("--out", self.out)):
            if not path.strip():
                raise ValueError(f"{flag} must be a path (not empty), got {path!r}")
        if (not self.seeds or any(not 0 <= s <= SEED_MAX for s in self.seeds)
                or len(set(self.seeds)) != len(self.seeds)):
            raise ValueError(f"--seeds must be distinct integers in [0, {SEED_MAX}], got {self.seeds}")
        if not 0 <= self.jobs <= JOBS_MAX:
            raise ValueError(f"--jobs must be in [0, {JOBS_MAX}], got {self.jobs}")
        if self.suites:
            from stepnft.suites import check_suites

            check_suites(self.suites)
        if not 1 <= self.suite_episodes <= EVAL_SEEDS_END:
            raise ValueError(f"--suite-episodes must be in [1, {EVAL_SEEDS_END}], got {self.suite_episodes}")
        self.variant_overrides()  # checks the items' shape and names

    def variant_overrides(self) -> dict[str, dict]:
        """``--variant-set`` as ``{variant: {field: value}}`` (values read as YAML); each variant
        must be among ``--algos``. The fields are checked where the variant's config is built."""
        from stepnft.config import read_yaml

        overrides: dict[str, dict] = {}
        for item in self.variant_set:
            key, sep, value = item.partition("=")
            # Variant names may hold dots (beta-0.5): the longest one that prefixes the key.
            names = sorted((n for n in variant_names() if key.startswith(n + ".")), key=len, reverse=True)
            if not sep or not names or not key[len(names[0]) + 1:]:
                raise ValueError(f"--variant-set {item}: expected VARIANT.FIELD=VALUE, e.g. ppo-shaped.lr=3e-5")
            name, name_field = names[0], key[len(names[0]) + 1:]
            if name not in self.algos:
                raise ValueError(f"--variant-set {item}: {name} is not among --algos ({', '.join(self.algos)})")
            if name_field == "name":
                raise ValueError(f"--variant-set {item}: a variant's algorithm is its own; pick another variant")
            overrides.setdefault(name, {})[name_field] = read_yaml(value)
        return overrides


def help_text() -> str:
    return f"{' '.join((CompareCommand.__doc__ or '').split())}\n\nvariants (--algos):\n{describe_variants()}\n"


def command_line(cmd: CompareCommand) -> str:
    """The ``stepnft compare`` command that reruns (resumes) ``cmd``."""
    tasks = f" --tasks {' '.join(cmd.tasks)}" if cmd.tasks else ""
    steps = f" --env-steps {cmd.env_steps}" if cmd.env_steps is not None else ""
    evals = f" --eval-episodes {cmd.eval_episodes}" if cmd.eval_episodes is not None else ""
    suites = f" --suites {','.join(cmd.suites)} --suite-episodes {cmd.suite_episodes}" if cmd.suites else ""
    variant_set = f" --variant-set {' '.join(cmd.variant_set)}" if cmd.variant_set else ""
    return (f"stepnft compare --config {cmd.config} --algos {','.join(cmd.algos)} "
            f"--seeds {' '.join(map(str, cmd.seeds))}{tasks}{steps}{evals}{suites}{variant_set} --out {cmd.out}")
