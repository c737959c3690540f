"""A deterministic bank of paraphrased language instructions for the 8 tasks.

Each instruction is built combinatorially: a *phrasing family* (sentence structure, e.g.
``question``: "could you {verb} {object} {goal}?") filled with the task's synonyms (verbs, object
nouns, goals), object descriptions (determiners, sizes, colours), then politeness (prefixes,
suffixes), casing, end punctuation and, sometimes, one typo. Every instruction carries its
family; validation holds out whole families (the same families for every task), so it measures
generalisation to unseen phrasings. Instructions are distinct after normalisation (case, spacing
and end punctuation ignored), and no text belongs to two tasks.

``generate_instructions(InstructionConfig())`` -> ``InstructionBank`` (10,000 by default, cached);
``episode_instruction(task, seed, split)`` gives an episode its instruction.
"""

from __future__ import annotations

import functools
import hashlib
from collections import Counter
from dataclasses import dataclass

import numpy as np

from anchordp3.schemas.tasks import TASK_NAMES, TaskPhrases, task_spec
from anchordp3.schemas.training import InstructionConfig

Split = str  # "train" or "val"


# -------------------------------------------------------------------------------------- families
@dataclass(frozen=True)
class Family:
    """A sentence structure. ``imperative`` families may take polite prefixes ("please ...")."""

    name: str
    templates: tuple[str, ...]
    imperative: bool = False
    question: bool = False
    terse: bool = False


FAMILIES: tuple[Family, ...] = (
    Family("imperative", ("{V} {O} {G}",), imperative=True),
    Family("pick_place", ("{P} {O} and {V} {it} {G}", "{P} {O} and then {V} {it} {G}"), imperative=True),
    Family("sequence", ("first {P} {O}, then {V} {it} {G}", "step one: {P} {O}. step two: {V} {it} {G}",
                        "{P} {O}; after that, {V} {it} {G}")),
    Family("question", ("can you {V} {O} {G}", "could you {V} {O} {G}", "would you {V} {O} {G}",
                        "will you {V} {O} {G}"), question=True),
    Family("desire", ("I want {O} {Vpp} {G}", "I'd like {O} {Vpp} {G}", "I would like {O} {Vpp} {G}",
                      "I need {O} {Vpp} {G}")),
    Family("obligation", ("{O} should be {Vpp} {G}", "{O} must be {Vpp} {G}", "{O} {has} to be {Vpp} {G}")),
    Family("goal_first", ("{G}, {V} {O}", "{G}: {V} {O}", "{G} is where {O} {goes}")),
    Family("terse", ("{bare} -> {T}", "{bare} to {T}", "{bare} => {T}", "{bare}: {T}"), terse=True),
    Family("help", ("help me {V} {O} {G}", "give me a hand and {V} {O} {G}", "I need your help to {V} {O} {G}"),
           imperative=True),
    Family("address", ("robot, {V} {O} {G}", "hey robot, {V} {O} {G}", "{V} {O} {G}, robot", "arm, {V} {O} {G}")),
    Family("task_goal", ("your task is to {V} {O} {G}", "the goal is to {V} {O} {G}", "the job is to {V} {O} {G}",
                         "mission: {V} {O} {G}")),
    Family("lets", ("let's {V} {O} {G}", "time to {V} {O} {G}", "go ahead and {V} {O} {G}")),
    Family("purpose", ("{V} {O} {G} {why}",), imperative=True),
    Family("negation", ("don't leave {O} where {it_is}; {V} {it} {G}", "{O} {is} in the wrong place, {V} {it} {G}"),
           imperative=True),
)
FAMILY_NAMES: tuple[str, ...] = tuple(f.name for f in FAMILIES)

_POLITE_PREFIX = ("please ", "kindly ", "now ", "please, ")
_INTERJECTION = ("ok, ", "okay, ", "alright, ", "so, ", "hey, ", "right, ", "um, ")
_SUFFIX = (" please", ", please", ", thanks", ", thank you", " for me", " now", " when you're ready", " carefully",
           " quickly", " right away", " if you can", " gently", ", cheers")
_KEYBOARD_ROWS = ("qwertyuiop", "asdfghjkl", "zxcvbnm")


# ------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Instruction:
    """One instruction of the bank; ``index`` is its position in the bank."""

    index: int
    text: str
    task: str
    task_id: int
    family: str
    split: Split


@dataclass(frozen=True, eq=False)
class InstructionBank:
    """All generated instructions and the family split."""

    instructions: tuple[Instruction, ...]
    val_families: frozenset[str]

    def __len__(self) -> int:
        return len(self.instructions)

    def split(self, name: Split) -> list[Instruction]:
        """The instructions of ``train`` or ``val``."""
        name = _split_name(name)
        return [i for i in self.instructions if i.split == name]

    def texts_and_labels(self, name: Split) -> tuple[list[str], list[int]]:
        """``(texts, task ids)`` of one split, in bank order."""
        rows = self.split(name)
        return [r.text for r in rows], [r.task_id for r in rows]

    def by_task(self, task: str, name: Split) -> list[Instruction]:
        """The instructions of ``task`` in split ``name``."""
        _check_task(task)
        return [i for i in self.split(name) if i.task == task]

    def for_episode(self, task: str, seed: int, split: Split = "train") -> Instruction:
        """A deterministic pick of ``task``'s ``split`` instructions for episode seed ``seed``."""
        pool = _pool(self, task, split)
        digest = hashlib.sha256(f"{task}/{seed}".encode()).digest()
        return pool[int.from_bytes(digest[:8], "little") % len(pool)]


@functools.lru_cache(maxsize=16)
def _pool(bank: InstructionBank, task: str, split: Split) -> tuple[Instruction, ...]:
    split = _split_name(split)
    pool = tuple(bank.by_task(task, split))
    if not pool:
        raise ValueError(f"instructions: no {split} instructions for task {task!r}")
    return pool


# ----------------------------------------------------------------------------------- generation
def split_families(seed: int, val_fraction: float) -> frozenset[str]:
    """The families held out for validation: ``round(val_fraction * 14)`` of them (at least 1,
    at most all but 1), chosen by ``seed``."""
    n = len(FAMILY_NAMES)
    k = min(max(1, round(val_fraction * n)), n - 1)
    order = np.random.default_rng([seed, 1]).permutation(n)
    return frozenset(FAMILY_NAMES[i] for i in sorted(order[:k]))


def generate_instructions(config: InstructionConfig | None = None) -> InstructionBank:
    """``config.count`` distinct instructions (default ``InstructionConfig()``: 10,000), as even over
    tasks (and, within a task, over families) as the phrase space allows. Same config -> same
    bank, instruction for instruction; cached per config."""
    return _generate(config or InstructionConfig())


@functools.lru_cache(maxsize=8)
def _generate(config: InstructionConfig) -> InstructionBank:
    val = split_families(config.seed, config.val_fraction)
    quotas = [config.count // len(TASK_NAMES) + (t < config.count % len(TASK_NAMES)) for t in range(len(TASK_NAMES))]
    seen: set[str] = set()  # normalised texts of every task so far: no text belongs to two tasks
    rows: list[tuple[str, str, str]] = []
    for t, task in enumerate(TASK_NAMES):
        rng = np.random.default_rng([config.seed, 2, t])
        phrases = task_spec(task).phrases
        done: Counter[str] = Counter()
        stalled: Counter[str] = Counter()
        made = 0
        attempts = 0
        while made < quotas[t]:
            live = [f for f in FAMILIES if stalled[f.name] < 200]
            if not live or attempts > 100 * quotas[t]:
                raise RuntimeError(f"instructions: only {made} distinct instructions for {task}, {quotas[t]} asked")
            attempts += 1
            family = min(live, key=lambda f: (done[f.name], FAMILY_NAMES.index(f.name)))
            text = _compose(rng, family, phrases, config.typo_prob)
            key = normalise(text)
            if key in seen:
                stalled[family.name] += 1
                continue
            seen.add(key)
            stalled[family.name] = 0
            done[family.name] += 1
            made += 1
            rows.append((text, task, family.name))
    instructions = tuple(
        Instruction(index=i, text=text, task=task, task_id=task_spec(task).task_id, family=fam,
                    split="val" if fam in val else "train")
        for i, (text, task, fam) in enumerate(rows)
    )
    return InstructionBank(instructions=instructions, val_families=val)


def episode_instruction(task: str, seed: int, split: Split = "train", config: InstructionConfig | None = None) -> Instruction:
    """The instruction of episode ``(task, seed)``: training episodes draw from the training
    families, evaluation episodes (``split="val"``) from the held-out ones. Deterministic."""
    return generate_instructions(config).for_episode(task, seed, _split_name(split))


def normalise(text: str) -> str:
    """The key two instructions are compared by: lower case, single spaces, no end punctuation."""
    return " ".join(text.lower().split()).rstrip(".!?").strip()


def _compose(rng: np.random.Generator, family: Family, p: TaskPhrases, typo_prob: float) -> str:
    """One instruction of ``family`` for the task of ``p``."""
    pick = lambda seq: seq[int(rng.integers(len(seq)))]
    noun = pick(p.nouns)
    colour = pick(p.colours)
    size = pick(p.sizes)
    head, rest = _split_quantity(noun)
    bare = _join(head, colour, rest)
    verb, participle = pick(p.verbs)
    goal = pick(p.goals)
    slots = {
        "O": _join(pick(p.dets), head, size, colour, rest),
        "V": verb, "Vpp": participle, "P": pick(p.picks), "G": goal, "T": pick(p.targets), "bare": bare,
        "why": pick(p.why),
        "it": "them" if p.plural else "it", "it_is": "they are" if p.plural else "it is",
        "is": "are" if p.plural else "is", "has": "have" if p.plural else "has", "goes": "go" if p.plural else "goes",
    }
    text = pick(family.templates).format(**slots)
    if family.terse:
        return _typo(rng, _case(rng, text), typo_prob)
    if family.imperative and rng.random() < 0.35:
        text = pick(_POLITE_PREFIX) + text
    elif rng.random() < 0.15:
        text = pick(_INTERJECTION) + text
    if rng.random() < 0.45:
        text += pick(_SUFFIX)
    text += "?" if family.question else pick((".", ".", "!", ""))
    return _typo(rng, _case(rng, text), typo_prob)


def _split_quantity(noun: str) -> tuple[str, str]:
    """``"three coloured blocks"`` -> ``("three", "coloured blocks")`` so adjectives go after the
    quantity ("three small coloured blocks", "pair of black shoes")."""
    for quantity in ("pair of", "three", "two"):
        if noun.startswith(quantity + " "):
            return quantity, noun[len(quantity) + 1:]
    return "", noun


def _join(*words: str) -> str:
    return " ".join(w for w in words if w)


def _case(rng: np.random.Generator, text: str) -> str:
    r = rng.random()
    if r < 0.6:
        return text[0].upper() + text[1:]
    if r < 0.96:
        return text
    return text.upper()


def _typo(rng: np.random.Generator, text: str, prob: float) -> str:
    """With probability ``prob``, one typo in one word of 4+ letters: swapped, dropped, doubled or
    neighbouring-key letter."""
    if rng.random() >= prob:
        return text
    words = text.split(" ")
    candidates = [i for i, w in enumerate(words) if sum(c.isalpha() for c in w) >= 4]
    if not candidates:
        return text
    wi = candidates[int(rng.integers(len(candidates)))]
    w = words[wi]
    letters = [i for i, c in enumerate(w) if c.isalpha()]
    pos = letters[int(rng.integers(1, len(letters)))]  # keep the first letter
    kind = int(rng.integers(4))
    if kind == 0 and pos + 1 < len(w) and w[pos + 1].isalpha():
        w = w[:pos] + w[pos + 1] + w[pos] + w[pos + 2:]
    elif kind == 1:
        w = w[:pos] + w[pos + 1:]
    elif kind == 2:
        w = w[:pos] + w[pos] + w[pos:]
    else:
        w = w[:pos] + _neighbour_key(rng, w[pos]) + w[pos + 1:]
    words[wi] = w
    return " ".join(words)


def _neighbour_key(rng: np.random.Generator, c: str) -> str:
    lower = c.lower()
    for row in _KEYBOARD_ROWS:
        k = row.find(lower)
        if k >= 0:
            options = [row[j] for j in (k - 1, k + 1) if 0 <= j < len(row)]
            out = options[int(rng.integers(len(options)))]
            return out.upper() if c.isupper() else out
    return c


def _split_name(name: str) -> Split:
    """``train`` or ``val`` (``validation`` is accepted for the latter, as the dataset index spells it)."""
    if name == "validation":
        return "val"
    if name not in ("train", "val"):
        raise ValueError(f"split: expected 'train' or 'val' ('validation'), got {name!r}")
    return name


def _check_task(task: str) -> None:
    if task not in TASK_NAMES:
        raise ValueError(f"task: unknown task {task!r}; choose one of {list(TASK_NAMES)}")
