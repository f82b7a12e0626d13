"""The specular constraint in path space (one and two vertices), Newton polish, path irradiance, canonical path order."""
