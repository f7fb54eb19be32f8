"""launch.conditions stand-in: IfCondition / UnlessCondition (text must be true/false/1/0)."""
from ._impl import (Condition, InvalidConditionExpressionError, evaluate_condition_expression,  # noqa: F401
                    normalize_to_list_of_substitutions)


class IfCondition(Condition):
    """True when the expression performs to true or 1 (false/0: False; anything else: error)."""

    def __init__(self, predicate_expression) -> None:
        self._expression = normalize_to_list_of_substitutions(predicate_expression)
        super().__init__(predicate=lambda context: evaluate_condition_expression(context, self._expression))


class UnlessCondition(Condition):
    """The negation of IfCondition (same validation)."""

    def __init__(self, predicate_expression) -> None:
        self._expression = normalize_to_list_of_substitutions(predicate_expression)
        super().__init__(predicate=lambda context: not evaluate_condition_expression(context, self._expression))
