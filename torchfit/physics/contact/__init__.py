"""Contact: the IPC self-contact barrier of a body's surface (ipctk) and the body's energy
as the sum of its elastic model and that barrier."""
from .barrier import ContactInputError, SelfContact
from .model import ElasticityWithContact

__all__ = ["ContactInputError", "ElasticityWithContact", "SelfContact"]
