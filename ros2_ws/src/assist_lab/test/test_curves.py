from assist_lab.curves import plot_curves

PNG = b'\x89PNG\r\n\x1a\n'


def test_draws_the_columns_it_has_and_refuses_what_it_cannot(tmp_path):
    csv_path = tmp_path / 'metrics.csv'
    csv_path.write_text('epoch,train_loss,val_loss\n1,3.0,3.5\n2,2.0,nan\n3,1.5,2.1\n')
    png = tmp_path / 'curve.png'
    assert plot_curves(csv_path, png, 'epoch', [['train_loss', 'val_loss', 'not_there']], smooth=2)
    assert png.read_bytes()[:8] == PNG
    assert not plot_curves(csv_path, tmp_path / 'none.png', 'epoch', [['nothing']])
    assert not plot_curves(tmp_path / 'missing.csv', tmp_path / 'none.png', 'epoch', [['train_loss']])
    (tmp_path / 'empty.csv').write_text('epoch,train_loss\n')
    assert not plot_curves(tmp_path / 'empty.csv', tmp_path / 'none.png', 'epoch', [['train_loss']])
    assert not (tmp_path / 'none.png').exists()
