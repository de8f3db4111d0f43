from hbis_torch.cli import entry_point

entry_point()
