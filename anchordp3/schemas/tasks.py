"""The task registry: every task's name, stable model id and instruction vocabulary, declared once.

A task is one ``TaskSpec`` here plus its simulator class (any module of ``sim/tasks/``), which
points at the spec (``spec = PLACE_MOUSE``) and takes its name, description and step limit from it. The spec lives here, apart from the
class, because the models and schemas need names, ids and phrases without importing the
simulator (no sapien outside ``sim/``). Everything else derives from the registry: ``TASK_NAMES``
(in id order), ``task_id``, the classifier's logits, the policy's per-task encoders, the
instruction bank. ``task_id`` values are stored in checkpoints (encoder index, logit index):
never renumber a task; a new one takes the next free id.

Phrases: ``verbs`` are (base, past participle) pairs; ``goals`` carry their preposition ("onto the
scale"); ``targets`` are bare goal nouns for terse commands; ``why`` are purpose clauses;
``plural`` picks it/them, is/are, ...
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TaskPhrases:
    """The words one task can be described with (see the module doc)."""

    nouns: tuple[str, ...]
    verbs: tuple[tuple[str, str], ...]
    picks: tuple[str, ...]
    goals: tuple[str, ...]
    targets: tuple[str, ...]
    why: tuple[str, ...]
    plural: bool = False
    dets: tuple[str, ...] = ("the",)
    sizes: tuple[str, ...] = ("",)
    colours: tuple[str, ...] = ("",)


_PLACE = (("place", "placed"), ("put", "put"), ("set", "set"), ("move", "moved"), ("lay", "laid"),
          ("position", "positioned"), ("rest", "rested"), ("drop", "dropped"))
_PICK = ("pick up", "grab", "take", "lift", "grasp", "get", "pick")
_SCALE_GOALS = ("on the electronic scale", "onto the electronic scale", "on the scale", "onto the scale",
                "onto the digital scale", "on top of the weighing scale", "on the scale's pad",
                "onto the kitchen scale", "on the weighing platform", "onto the pad of the scale")
_SCALE_TARGETS = ("scale", "electronic scale", "digital scale", "weighing scale", "the scale")
_SCALE_WHY = ("so it can be weighed", "so we can weigh it", "to weigh it", "to check its weight",
              "so I can see how heavy it is", "for weighing")
_SIZES = ("", "small", "little", "compact")
_BLOCK_NOUNS = ("red, green and blue blocks", "red, green, and blue cubes", "three coloured blocks",
                "three colored blocks", "RGB blocks", "three blocks", "coloured cubes", "blocks",
                "red, blue and green blocks", "three cubes")


@dataclass(frozen=True)
class TaskSpec:
    """One task: its name, its stable model id, one sentence a person would say for it, its step
    limit (control steps at 50 Hz), the words its instructions are made of."""

    name: str
    task_id: int
    description: str
    step_limit: int
    phrases: TaskPhrases


SPECS: dict[str, TaskSpec] = {}


def register(spec: TaskSpec) -> TaskSpec:
    """Add ``spec`` to the registry; a name or id used twice is an error."""
    if spec.name in SPECS or any(s.task_id == spec.task_id for s in SPECS.values()):
        raise ValueError(f"task {spec.name!r} (id {spec.task_id}): name or id already registered")
    SPECS[spec.name] = spec
    return spec


PLACE_MOUSE = register(TaskSpec(
    name="place_mouse", task_id=0,
    description="Pick up the mouse and place it on the electronic scale.",
    step_limit=800,
    phrases=TaskPhrases(
        nouns=("mouse", "computer mouse", "wireless mouse", "PC mouse", "optical mouse", "mouse device"),
        verbs=_PLACE, picks=_PICK, goals=_SCALE_GOALS, targets=_SCALE_TARGETS, why=_SCALE_WHY,
        dets=("the", "that", "this"), sizes=_SIZES,
        colours=("", "black", "white", "grey", "gray", "blue", "red", "pink"),
    ),
))


PLACE_STAPLER = register(TaskSpec(
    name="place_stapler", task_id=1,
    description="Pick up the stapler and place it on the electronic scale.",
    step_limit=800,
    phrases=TaskPhrases(
        nouns=("stapler", "office stapler", "desk stapler", "paper stapler", "stapling tool", "staple gun"),
        verbs=_PLACE, picks=_PICK, goals=_SCALE_GOALS, targets=_SCALE_TARGETS, why=_SCALE_WHY,
        dets=("the", "that", "this"), sizes=_SIZES, colours=("", "black", "red", "blue", "green", "grey", "gray"),
    ),
))


PLACE_BELL = register(TaskSpec(
    name="place_bell", task_id=2,
    description="Pick up the bell and place it on the electronic scale.",
    step_limit=800,
    phrases=TaskPhrases(
        nouns=("bell", "service bell", "desk bell", "call bell", "counter bell", "reception bell", "hotel bell"),
        verbs=_PLACE, picks=_PICK, goals=_SCALE_GOALS, targets=_SCALE_TARGETS, why=_SCALE_WHY,
        dets=("the", "that", "this"), sizes=_SIZES, colours=("", "silver", "gold", "golden", "copper", "shiny"),
    ),
))


BLOCKS_RANKING_RGB = register(TaskSpec(
    name="blocks_ranking_rgb", task_id=3,
    description="Put the red, green and blue blocks in a row, in that order from left to right.",
    step_limit=2000,
    phrases=TaskPhrases(
        nouns=_BLOCK_NOUNS, plural=True,
        verbs=(("arrange", "arranged"), ("line up", "lined up"), ("sort", "sorted"), ("order", "ordered"),
               ("rank", "ranked"), ("put", "put"), ("lay out", "laid out"), ("place", "placed")),
        picks=("pick up", "grab", "take", "move"),
        goals=("in a row from left to right as red, green, blue", "in red-green-blue order from left to right",
               "left to right in the order red, green, blue", "in RGB order from left to right",
               "in a line with red on the left, green in the middle and blue on the right",
               "so they read red, green, blue from left to right", "side by side in the order red, green, blue",
               "in a horizontal row, red first, then green, then blue"),
        targets=("row in RGB order", "left to right R G B", "red-green-blue row", "RGB line", "row, red to blue"),
        why=("so the colours are in order", "to sort them by colour", "so they are ranked by colour",
             "so the row reads RGB"),
        dets=("the", "these", "those", "all the"), sizes=("", "small", "little", "toy"),
    ),
))


STACK_BLOCKS_THREE = register(TaskSpec(
    name="stack_blocks_three", task_id=4,
    description="Stack the three blocks at the target spot: red at the bottom, then green, then blue on top.",
    step_limit=2000,
    phrases=TaskPhrases(
        nouns=_BLOCK_NOUNS, plural=True,
        verbs=(("stack", "stacked"), ("pile", "piled"), ("pile up", "piled up"), ("put", "put"),
               ("place", "placed"), ("build", "built"), ("assemble", "assembled")),
        picks=("pick up", "grab", "take", "lift"),
        goals=("on top of each other", "into a tower", "into a single stack", "one on top of another",
               "with red at the bottom, green in the middle and blue on top",
               "into a tower: red, then green, then blue", "into a three-block tower at the target spot",
               "into one pile, red first and blue last", "vertically at the target spot"),
        targets=("tower", "stack", "one tower", "red-green-blue tower", "single pile"),
        why=("to build a tower", "so they form a tower", "to make a stack", "so only one pile is left"),
        dets=("the", "these", "those", "all the"), sizes=("", "small", "little", "toy"),
    ),
))


PLACE_DUAL_SHOES = register(TaskSpec(
    name="place_dual_shoes", task_id=5,
    description="Use both arms to put the pair of shoes side by side on the mat, toes pointing forward.",
    step_limit=1800,  # 3 x RoboTwin's 600 (its frames ~16.7 Hz, our control 50 Hz)
    phrases=TaskPhrases(
        nouns=("shoes", "pair of shoes", "two shoes", "sneakers", "pair of sneakers", "trainers",
               "left and right shoes", "footwear"),
        plural=True,
        verbs=(("place", "placed"), ("put", "put"), ("set", "set"), ("line up", "lined up"),
               ("arrange", "arranged"), ("move", "moved"), ("align", "aligned")),
        picks=("pick up", "grab", "take", "lift"),
        goals=("side by side at the target", "next to each other at their target spots", "neatly at the marked spots",
               "together on the mat", "at their targets, toes pointing forward", "as a pair in the middle of the table",
               "upright at the target area", "paired up at the goal positions"),
        targets=("target spots", "side by side", "mat", "their targets", "a neat pair"),
        why=("so they are tidy", "to tidy them up", "so they form a neat pair", "so they're ready to wear"),
        dets=("the", "these", "those", "my"), sizes=("", "little"), colours=("", "black", "white", "brown", "grey"),
    ),
))


PUT_BOTTLES_DUSTBIN = register(TaskSpec(
    name="put_bottles_dustbin", task_id=6,
    description="Put all the bottles into the dustbin.",
    step_limit=3000,  # 3 x RoboTwin's 1000 (its frames ~16.7 Hz, our control 50 Hz)
    phrases=TaskPhrases(
        nouns=("bottles", "plastic bottles", "empty bottles", "drink bottles", "water bottles", "soda bottles",
               "three bottles", "used bottles"),
        plural=True,
        verbs=(("put", "put"), ("throw", "thrown"), ("drop", "dropped"), ("toss", "tossed"), ("place", "placed"),
               ("move", "moved"), ("dump", "dumped"), ("discard", "discarded")),
        picks=("pick up", "grab", "collect", "take", "gather"),
        goals=("into the dustbin", "in the dustbin", "in the trash can", "into the bin", "in the wastebasket",
               "into the garbage can", "into the rubbish bin", "in the recycling bin", "into the waste bin"),
        targets=("dustbin", "bin", "trash", "trash can", "garbage", "recycling"),
        why=("to clean up the table", "to tidy the table", "for recycling", "so the table is clear"),
        dets=("the", "all the", "all of the", "these", "those"), sizes=("", "small"),
    ),
))


PLACE_PHONE_STAND = register(TaskSpec(
    name="place_phone_stand", task_id=7,
    description="Pick up the phone and put it on the phone stand.",
    step_limit=1200,  # 3 x RoboTwin's 400 (its frames ~16.7 Hz, our control 50 Hz)
    phrases=TaskPhrases(
        nouns=("phone", "smartphone", "mobile phone", "cell phone", "cellphone", "mobile", "handset"),
        verbs=(("place", "placed"), ("put", "put"), ("set", "set"), ("rest", "rested"), ("lean", "leaned"),
               ("mount", "mounted"), ("stand", "stood"), ("position", "positioned")),
        picks=_PICK,
        goals=("on the phone stand", "onto the stand", "on the phone holder", "onto the phone dock",
               "into the phone holder", "on the charging stand", "against the stand", "upright on the stand",
               "on the little stand", "onto its stand"),
        targets=("stand", "phone stand", "holder", "dock", "phone holder"),
        why=("so it can charge", "so it stands upright", "so I can see the screen", "so it doesn't lie flat"),
        dets=("the", "that", "this", "my"), sizes=_SIZES, colours=("", "black", "white", "silver", "blue"),
    ),
))


TASK_NAMES: tuple[str, ...] = tuple(s.name for s in sorted(SPECS.values(), key=lambda s: s.task_id))
"""Every task, in model-id order (``place_object_scale`` split into mouse / stapler / bell)."""
if [SPECS[n].task_id for n in TASK_NAMES] != list(range(len(TASK_NAMES))):
    raise ValueError("task ids must be 0..n-1 without gaps")


def task_spec(name: str) -> TaskSpec:
    """The spec of task ``name``; a clear error lists the names."""
    try:
        return SPECS[name]
    except KeyError:
        raise ValueError(f"task: unknown task {name!r}; choose one of {list(TASK_NAMES)}") from None


def task_id(name: str) -> int:
    """The stable model id of task ``name`` (its index in ``TASK_NAMES``)."""
    return task_spec(name).task_id
