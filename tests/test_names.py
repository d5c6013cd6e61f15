from stepnft.names import split_names


def test_split_names_reads_lists_commas_and_none():
    assert split_names(["reach-v3,push-v3", " door-open-v3 "]) == ["reach-v3", "push-v3", "door-open-v3"]
    assert split_names("a, ,b,") == ["a", "b"]
    assert split_names(None) == []
    assert split_names([]) == []
