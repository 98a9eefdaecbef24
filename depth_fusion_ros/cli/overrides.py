"""``--set OWNER.KEY=VALUE`` options, shared by the subcommands that take them."""

from __future__ import annotations


def parse_overrides(items: list[str], owner: str = 'STAGE') -> dict[str, dict[str, object]]:
    """``['fusion.mode=fast', 'fusion_node.fusion.mode=exact']`` ->
    ``{'fusion': {'mode': 'fast'}, 'fusion_node': {'fusion.mode': 'exact'}}``.

    The owner (a stage or a node) is what comes before the first dot; the value is parsed as
    YAML so numbers, booleans and lists get their types (``96`` is an int, ``true`` a bool).
    """
    import yaml

    out: dict[str, dict[str, object]] = {}
    for item in items:
        key, sep, value = item.partition('=')
        name, dot, param = key.partition('.')
        if not sep or not dot or not name or not param:
            raise ValueError(f'--set expects {owner}.KEY=VALUE, got {item!r}')
        out.setdefault(name, {})[param] = yaml.safe_load(value)
    return out
