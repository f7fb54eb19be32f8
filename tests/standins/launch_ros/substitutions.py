"""launch_ros.substitutions stand-in: FindPackageShare, FindPackagePrefix (ament index)."""
from ament_index_python.packages import get_package_prefix, get_package_share_directory
from launch._impl import Substitution, normalize_to_list_of_substitutions, perform_substitutions


class FindPackageShare(Substitution):
    """share/<package> of a package in the ament index."""

    def __init__(self, package) -> None:
        self.package = normalize_to_list_of_substitutions(package)

    def perform(self, context) -> str:
        return get_package_share_directory(perform_substitutions(context, self.package))


class FindPackagePrefix(FindPackageShare):
    """The install prefix of a package in the ament index."""

    def perform(self, context) -> str:
        return get_package_prefix(perform_substitutions(context, self.package))
