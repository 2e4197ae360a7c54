"""jaxcal.data: the rows container and the generic readers (tables); a model's own
file formats are the model's (:attr:`jaxcal.model.Model.file_readers`)."""
